"""A Leica laser tracker through its emScon TPI interface (``docs/tracker.md``,
"emScon"): ``kind = "laser-tracker"``, ``driver = "emscon"``, ``address = "host[:port]"``
(port 700 by default).

At connect: the system status (serial, firmware, laser, weather monitor), the units
cellcal works in (mm, degrees, °C, hPa, %RH; read back, a tracker that keeps others is
refused), the warm-up waited for (up to ``warmup_timeout_s``, the laser's state logged),
system settings (the tracker's own frame: cellcal registers frames itself; unsolicited
messages on), the air (the tracker's meteo station, or the configuration's values),
an initialisation when the tracker needs one (up to ``initialize_timeout_s``),
stationary mode with ``measure_time_ms``, extended statistics (each result with its
covariance) and the reflector chosen by name.

``measure(n)`` takes ``n`` stationary measurements. A broken beam (the tracker's "no
stationary result", or "not ready" at the start) is recovered as ``relock`` says —
``wait`` for the tracker to lock again, or send ``find-reflector`` or ``bird-bath`` —
and the lost measurement is taken again; at most ``2 n`` attempts and ``beam_retries``
breaks, the series' note saying what happened.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from cellcal.clock import Clock, WallClock
from cellcal.device_options import SensorOptions
from cellcal.drivers import emscon_packets as p
from cellcal.drivers.base import DeviceContext, DeviceDescription, Series, label, naming_errors
from cellcal.drivers.base import host_port as split_address
from cellcal.drivers.emscon_link import DEFAULT_PORT, EmsconLink, EmsconStatusError
from cellcal.errors import DeviceError, NoTargetError

log = logging.getLogger("cellcal.drivers.emscon")

Relock = Literal["wait", "find-reflector", "bird-bath"]
UNITS = (p.MILLIMETRE, p.DEGREE, p.CELSIUS, p.HECTOPASCAL, p.RELATIVE_HUMIDITY)
#: how often the warm-up and a lost beam are polled (s)
POLL_S = 1.0
#: ES_LaserProcessorStatus, in words
LASER_STATES = {
    0: "laser processor not reachable",
    1: "no laser processor",
    2: "heating up",
    3: "ready",
    4: "unable to stabilise",
    5: "laser off",
}


class EmsconOptions(SensorOptions):
    """A ``[[sensor]]`` with ``driver = "emscon"`` (``docs/tracker.md``)."""

    kind: Literal["laser-tracker"] = "laser-tracker"
    driver: Literal["emscon"] = "emscon"
    reflector: Annotated[str, Field(min_length=1, max_length=31)] | None = None
    meteo: Literal["station", "manual"] = "station"
    temperature_c: Annotated[float, Field(ge=-20, le=60)] | None = None
    pressure_hpa: Annotated[float, Field(ge=500, le=1100)] | None = None
    humidity_pct: Annotated[float, Field(ge=0, le=100)] | None = None
    measure_time_ms: Annotated[int, Field(ge=10, le=60000)] = 1000
    relock: Relock = "wait"
    warmup_timeout_s: Annotated[float, Field(ge=0, le=7200)] = 1800.0
    initialize_timeout_s: Annotated[float, Field(gt=0, le=3600)] = 600.0
    timeout_s: Annotated[float, Field(gt=0, le=600)] = 10.0
    beam_retries: Annotated[int, Field(ge=0, le=100)] = 3
    beam_wait_s: Annotated[float, Field(ge=0, le=3600)] = 30.0

    @model_validator(mode="after")
    def _manual_air(self) -> EmsconOptions:
        air = (self.temperature_c, self.pressure_hpa, self.humidity_pct)
        if self.meteo == "manual" and None in air:
            raise ValueError('meteo = "manual" needs temperature_c, pressure_hpa and humidity_pct')
        if self.meteo == "station" and any(v is not None for v in air):
            raise ValueError(
                'temperature_c, pressure_hpa, humidity_pct are for meteo = "manual"; '
                'with meteo = "station" the tracker measures the air'
            )
        return self


class EmsconTracker:
    """A tracker at ``host[:port]``; implements the engine's PositionSensor Protocol."""

    def __init__(
        self,
        options: EmsconOptions,
        clock: Clock | None = None,
        report: Callable[[str, str], None] | None = None,
    ) -> None:
        self.options = options
        self.name = options.name
        self.address = options.address
        self.label = self.name if "tracker" in self.name.lower() else f"tracker {self.name}"
        host, port = split_address(self.address, DEFAULT_PORT)
        # the port named even when it is the default (TPI's 700), in every message
        shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self.where = label(self.label, shown if self.address else "")
        self.link = EmsconLink(self.where, host, port, options.timeout_s)
        self.clock = clock or WallClock()
        self.serial: str | None = None
        self.firmware: str | None = None
        self.model: str | None = None
        self.statistic = p.STATISTIC_EXTENDED
        self.reflector_id: int | None = None
        self.last_range_mm = 0.0
        self._report = report

    def _say(self, message: str) -> None:
        """What the tracker is doing while it gets ready: logged, and reported to the
        service's status when it asked (``DeviceContext.report``)."""
        log.warning("%s: %s", self.where, message)
        if self._report is not None:
            self._report(self.name, message)

    @classmethod
    def from_options(cls, options: EmsconOptions, context: DeviceContext) -> EmsconTracker:
        return cls(options, context.clock, context.report)

    # ------------------------------------------------------------------ connection

    @naming_errors
    def connect(self) -> None:
        self.link.open()
        try:
            self._handshake()
        except BaseException:
            self.link.close()
            raise

    def close(self) -> None:
        self.link.close()

    def _status(self) -> tuple[int, ...]:
        return self.link.request(p.GET_SYSTEM_STATUS).values

    def _handshake(self) -> None:
        status = self._status()
        self.firmware = ".".join(str(v) for v in status[4:7])
        self.serial = str(status[9])
        self.link.request(p.SET_UNITS, *UNITS)
        units = tuple(self.link.request(p.GET_UNITS).values)
        if units != UNITS:
            raise DeviceError(
                f"{self.where}: SetUnits to mm, degrees, °C, hPa, %RH was answered OK but the "
                f"tracker reports units {units}: refused (the results would be in other units)"
            )
        self._identify()
        self._warm_up(status)
        settings = self.link.request(p.GET_SYSTEM_SETTINGS).values
        station = self.options.meteo == "station"
        weather = p.WEATHER_READ_AND_REFRACT if station else p.WEATHER_NOT_CONNECTED
        # the tracker's own frame (no transformation, no station orientation), keep the
        # last position on a break, unsolicited messages on, no position stream, no try
        # mode; the nivel and camera flags as the tracker has them
        flags = (weather, 0, 0, 1, 1, 0, 0, int(settings[7]), int(settings[8]))
        self.link.request(p.SET_SYSTEM_SETTINGS, *flags)
        self._air(station)
        if int(status[1]) != p.TRACKER_PROCESSOR_INITIALIZED:
            self._initialise()
        self.link.request(p.SET_MEASUREMENT_MODE, p.STATIONARY)
        self.link.request(p.SET_COORDINATE_SYSTEM_TYPE, p.RHR)
        self.link.request(p.SET_STATIONARY_MODE_PARAMS, self.options.measure_time_ms, 1)
        self.link.request(p.SET_STATISTIC_MODE, p.STATISTIC_EXTENDED, p.STATISTIC_STANDARD)
        if self.options.reflector is not None:
            self._choose_reflector(self.options.reflector)

    def _identify(self) -> None:
        try:
            info = self.link.request(p.GET_TRACKER_INFO).values
        except EmsconStatusError as exc:
            log.info("%s: no tracker info (%s)", self.where, exc)
            return
        self.model = p.decode_name(info[1]) or None
        self.serial = str(info[2]) or self.serial

    def _warm_up(self, status: tuple[Any, ...]) -> None:
        """Wait while the laser heats up (the tracker's own state logged)."""
        start = time.monotonic()
        deadline = start + self.options.warmup_timeout_s
        while int(status[2]) != p.LASER_READY:
            if time.monotonic() >= deadline:
                raise DeviceError(
                    f"{self.where}: the sensor is not warmed up after "
                    f"{self.options.warmup_timeout_s:g} s (laser state {status[2]}); raise "
                    "warmup_timeout_s or wait for the tracker's warm-up to end"
                )
            waited = time.monotonic() - start
            self._say(
                f"laser warming up ({LASER_STATES.get(int(status[2]), status[2])}); waited "
                f"{waited:.0f} of {self.options.warmup_timeout_s:g} s"
            )
            time.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
            status = self._status()

    def _air(self, station: bool) -> None:
        if station:
            info = self.link.request(p.GET_METEO_STATION_INFO).values
            if int(info[0]) == 0:
                raise DeviceError(
                    f"{self.where}: the tracker has no meteo station: set meteo = "
                    '"manual" with temperature_c, pressure_hpa and humidity_pct'
                )
            return
        o = self.options
        try:
            self.link.request(
                p.SET_ENVIRONMENT_PARAMS, o.temperature_c, o.pressure_hpa, o.humidity_pct
            )
        except EmsconStatusError as exc:
            if exc.status != p.METEO_OUT_OF_RANGE:
                raise
            raise DeviceError(
                f"{self.where}: the tracker refuses the configured air ({o.temperature_c} °C, "
                f"{o.pressure_hpa} hPa, {o.humidity_pct} %RH) as out of its range"
            ) from None

    def _initialise(self) -> None:
        """Initialize: the reply comes when it is done (minutes on a real tracker); a
        tracker still warming up is waited for first."""
        self._say(f"initialising (up to {self.options.initialize_timeout_s:g} s)")
        try:
            self.link.request(p.INITIALIZE, timeout_s=self.options.initialize_timeout_s)
        except EmsconStatusError as exc:
            if exc.status != p.SENSOR_NOT_WARMED_UP:
                raise DeviceError(f"{self.where}: initialisation failed: {exc}") from None
            self._warm_up(self._status())
            self.link.request(p.INITIALIZE, timeout_s=self.options.initialize_timeout_s)

    def _reflectors(self) -> dict[str, int]:
        self.link.send(p.GET_REFLECTORS)
        first = self.link.reply(p.GET_REFLECTORS)
        replies = [first]
        total = int(first.values[0])
        for _ in range(1, max(1, min(total, 64))):
            replies.append(self.link.reply(p.GET_REFLECTORS))
        return {p.decode_name(r.values[4]): int(r.values[1]) for r in replies}

    def _choose_reflector(self, name: str) -> None:
        known = self._reflectors()
        if name not in known:
            listed = ", ".join(repr(k) for k in known) or "none"
            raise DeviceError(f"{self.where}: no reflector {name!r}; the tracker lists {listed}")
        self.link.request(p.SET_REFLECTOR, known[name])
        self.reflector_id = known[name]

    def describe(self) -> DeviceDescription:
        return DeviceDescription(
            self.name,
            "laser-tracker/emscon",
            self.address,
            "Leica",
            self.model,
            self.firmware,
            self.serial,
        )

    # ------------------------------------------------------------------ measuring

    def _one(self) -> p.Measurement:
        """One stationary measurement; NoTargetError when the beam is broken."""
        try:
            self.link.request(p.START_MEASUREMENT)
        except EmsconStatusError as exc:
            lost = (p.MEAS_STATUS_NOT_READY_ERROR, p.SYSTEM_NOT_READY, p.NO_STATIONARY_RESULT)
            if exc.status in lost:
                raise NoTargetError(f"{self.where}: {p.status_text(exc.status)}") from None
            raise
        wait = self.options.measure_time_ms / 1000.0 + self.options.timeout_s
        deadline = time.monotonic() + wait
        while True:
            packet = self.link.read_packet(deadline, "for the measurement's result")
            if isinstance(packet, p.Measurement):
                if packet.status != p.OK:
                    raise NoTargetError(f"{self.where}: result {p.status_text(packet.status)}")
                return packet
            if isinstance(packet, p.ErrorPacket) and packet.command in (p.START_MEASUREMENT, 0):
                if packet.status in (p.NO_STATIONARY_RESULT, p.MEAS_STATUS_NOT_READY_ERROR):
                    raise NoTargetError(f"{self.where}: {p.status_text(packet.status)}")
                raise self.link.refused(p.START_MEASUREMENT, packet.status)
            self.link.note(packet, "for the measurement's result")

    def _relock(self) -> None:
        """After a break: the relock configured, then wait until the tracker sees its
        reflector (``beam_wait_s``)."""
        how = self.options.relock
        if how == "find-reflector":
            self.link.request(
                p.FIND_REFLECTOR, self.last_range_mm, timeout_s=self.options.beam_wait_s + 10
            )
        elif how == "bird-bath":
            self.link.request(p.GO_BIRD_BATH, timeout_s=self.options.beam_wait_s + 10)
        deadline = time.monotonic() + self.options.beam_wait_s
        while True:
            info = self.link.request(p.GET_MEASUREMENT_STATUS_INFO).values
            if int(info[1]) & p.REFLECTOR_FOUND:
                return
            if time.monotonic() >= deadline:
                raise NoTargetError(
                    f"{self.where}: no reflector found {self.options.beam_wait_s:g} s after "
                    f"the beam broke (relock = {how!r})"
                )
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))

    @naming_errors
    def measure(self, n: int, rate_hz: float) -> Series:
        """``n`` stationary measurements (``rate_hz`` is not used: each takes
        ``measure_time_ms``), each with its covariance and the air it was taken in; the
        device time of each is when its result arrived (the result carries no time)."""
        if not 1 <= n <= 10000:
            raise DeviceError(f"{self.where}: measure: n in 1..10000, got {n}")
        host: list[float] = []
        device: list[float] = []
        taken: list[p.Measurement] = []
        breaks = failed = 0
        problems: list[str] = []
        while len(taken) < n and len(taken) + failed < 2 * n:
            try:
                m = self._one()
            except NoTargetError as exc:
                breaks += 1
                failed += 1
                problems.append(
                    f"{str(exc).removeprefix(self.where + ': ')} at sample {len(taken) + 1}"
                )
                if breaks > self.options.beam_retries:
                    problems.insert(
                        0,
                        f"beam broken {breaks} times, beam_retries is {self.options.beam_retries}",
                    )
                    break
                try:
                    self._relock()
                except NoTargetError as lost:
                    problems.insert(0, str(lost).removeprefix(self.where + ": "))
                    break
                continue
            host.append(self.clock.now())
            device.append(time.monotonic())  # a result carries no time: when it came
            taken.append(m)
            self.last_range_mm = float(np.linalg.norm(m.xyz))
        if not taken:
            why = "; ".join(problems[:3])
            raise NoTargetError(f"{self.where}: no measurement in {failed} attempts ({why})")
        note = ""
        if problems:
            why = "; ".join(problems[:3]) + ("; …" if len(problems) > 3 else "")
            note = f"{len(taken)} of {n} samples after {len(taken) + failed} attempts: {why}"
        cov = np.stack([m.covariance() for m in taken])
        meteo = np.array([(m.temperature_c, m.pressure_hpa, m.humidity_pct) for m in taken])
        finite = bool(np.isfinite(cov).all() and np.isfinite(meteo).all())
        if not finite or not all(math.isfinite(v) for m in taken for v in m.xyz):
            raise DeviceError(f"{self.where}: a result with a value that is not a number")
        return Series(
            self.name,
            np.array(host),
            np.array(device),
            np.array([m.xyz for m in taken], dtype=np.float64),
            retries=breaks,
            cov=cov,
            meteo=meteo,
            note=note,
        )
