"""The emScon twin's tracker (``docs/tracker.md``, "emScon"): what an AT401 answers to
each command of a campaign, as packets (``cellcal/drivers/emscon_packets.py``), with
the time things take. Pure: :meth:`EmsconState.handle` takes a command and the wall
time and returns the packets to send now; packets due later (the end of an
initialisation, a measurement's result, the beam back) come out of :meth:`due`. The
server (``emscon_server.py``) moves bytes.

What it models:

* the sensor warms up for ``warmup_s`` after the twin starts: Initialize and
  StartMeasurement answer "sensor not warmed up" (10012) meanwhile, and the system
  status shows the laser heating up;
* Initialize takes ``initialize_s`` × ``time_scale``; the reply comes at the end, after
  the status changes (busy, initialised, ready); commands in between answer "busy";
* a stationary measurement takes its measuring time × ``time_scale``; its result is a
  type 9 packet (with the covariance of the noise it drew) in extended statistic mode,
  a type 2 one in standard mode;
* the beam breaks on every ``beam_break_every``-th measurement: the result is an error
  packet (10009, no stationary result) and, with unsolicited messages on, "not ready";
  the beam is back ``beam_restore_s`` later ("ready") or at FindReflector or GoBirdBath
  (the twin has no nest: the bird bath relocks like a search);
* units: what SetUnits sets is what results, environment values and ranges are in;
* the meteo: a station (``meteo_station``) reports the cell's air; without one the values
  of SetEnvironmentParams are used; values out of range answer 57.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers import emscon_packets as p

#: Length units (ES_LengthUnit) in mm; temperature (ES_TemperatureUnit) as (scale, offset)
#: from °C; pressure (ES_PressureUnit) in hPa.
LENGTH_MM = {0: 1000.0, 1: 1.0, 2: 0.001, 3: 304.8, 4: 914.4, 5: 25.4}
TEMPERATURE = {0: (1.0, 0.0), 1: (1.8, 32.0)}
PRESSURE_HPA = {0: 1.0, 1: 1.0, 2: 10.0, 3: 1.33322, 4: 68.9476, 5: 2.49089, 6: 33.8639}
#: What the twin takes for air (°C, hPa, %RH) before SetEnvironmentParams.
T_RANGE, P_RANGE, RH_RANGE = (-20.0, 60.0), (500.0, 1100.0), (0.0, 100.0)
#: The reflectors it knows: (id, name, ES_TargetType, surface offset mm).
REFLECTORS = ((7, "RRR 1.5in", 5, 0.0), (8, "RRR 0.5in", 6, 0.0), (9, "TBR 0.5in", 9, 0.0))
SERIAL = 392012
FIRMWARE = (3, 6, 1254)


@dataclass(frozen=True)
class EmsconFaults:
    """Faults of the twin (all off by default); times in wall seconds."""

    warmup_s: float = 0.0
    beam_break_every: int = 0
    beam_restore_s: float = 0.2

    def __post_init__(self) -> None:
        for name in ("warmup_s", "beam_restore_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"EmsconFaults.{name} must be finite and >= 0, got {value}")
        if self.beam_break_every < 0:
            raise ValueError("EmsconFaults.beam_break_every must be >= 0")


@dataclass
class _Settings:
    units: tuple[int, int, int, int, int] = (1, 0, 0, 0, 0)  # mm, rad, °C, mbar, RH
    environment: tuple[float, float, float] = (20.0, 1013.25, 45.0)  # °C, hPa, %RH
    mode: int = p.STATIONARY
    coordinates: int = p.RHR
    measure_ms: int = 1000
    use_adm: int = 1
    reflector: int = REFLECTORS[0][0]
    system: tuple[int, ...] = (p.WEATHER_READ_AND_REFRACT, 0, 1, 1, 1, 0, 0, 1, 0)
    statistic: tuple[int, int] = (p.STATISTIC_STANDARD, p.STATISTIC_STANDARD)


@dataclass
class EmsconState:
    """One tracker. ``sample()`` draws one noisy target position (mm, tracker frame) and
    ``covariance()`` gives that noise's 3×3 covariance (mm²) where the target is now."""

    sample: Callable[[], Array]
    covariance: Callable[[], Array]
    started: float
    faults: EmsconFaults = EmsconFaults()
    time_scale: float = 0.0
    initialize_s: float = 20.0
    meteo_station: bool = True
    air: tuple[float, float, float] = (20.0, 1013.25, 45.0)
    settings: _Settings = field(default_factory=_Settings)
    initialized: bool = False
    beam: bool = True
    measurements: int = 0
    busy_until: float | None = None
    restore_at: float | None = None
    pending: list[tuple[float, bytes]] = field(default_factory=list)
    last_status: int = p.OK

    # -- time

    def due(self, now: float) -> list[bytes]:
        """The packets whose time has come, in order."""
        ready = []
        if self.restore_at is not None and now >= self.restore_at:
            ready += self._relock()
        ready += [data for at, data in self.pending if at <= now]
        self.pending = [(at, data) for at, data in self.pending if at > now]
        if self.busy_until is not None and now >= self.busy_until:
            self.busy_until = None
        return ready

    def next_due(self) -> float | None:
        times = [at for at, _ in self.pending]
        if self.restore_at is not None:
            times.append(self.restore_at)
        return min(times) if times else None

    def warm(self, now: float) -> bool:
        return now - self.started >= self.faults.warmup_s

    # -- commands

    def handle(self, command: p.Command, now: float) -> list[bytes]:
        """The packets a command is answered with now (more may follow from :meth:`due`)."""
        c, args = command.command, command.params
        if self.busy_until is not None and now < self.busy_until:
            return [self._reply(c, p.SERVER_BUSY)]
        handler = _HANDLERS.get(c)
        if handler is not None:
            return handler(self, args, now)
        return [self._reply(c, p.OK, *self._get(c, now))]

    def _reply(self, command: int, status: int, *values: object) -> bytes:
        self.last_status = status
        return p.encode_reply(command, status, *values)

    def _event(self, code: int) -> list[bytes]:
        unsolicited = bool(self.settings.system[4])
        return [p.encode_status_change(code)] if unsolicited else []

    def _at(self, delay: float, data: bytes, now: float) -> None:
        self.pending.append((now + delay, data))

    def _initialize(self, args: tuple[Any, ...], now: float) -> list[bytes]:
        if not self.warm(now):
            return [self._reply(p.INITIALIZE, p.SENSOR_NOT_WARMED_UP)]
        delay = self.initialize_s * self.time_scale
        self.busy_until = now + delay
        for code in (p.INITIALIZATION_STATUS_CHANGED, p.MEAS_READY):
            for data in self._event(code):
                self._at(delay, data, now)
        self._at(delay, p.encode_reply(p.INITIALIZE, p.OK), now)
        self.initialized = True
        self.beam = True
        return self._event(p.MEAS_BUSY)

    def _start(self, args: tuple[Any, ...], now: float) -> list[bytes]:
        if not self.warm(now):
            return [self._reply(p.START_MEASUREMENT, p.SENSOR_NOT_WARMED_UP)]
        if not self.initialized:
            return [self._reply(p.START_MEASUREMENT, p.TRACKER_NOT_INITIALIZED)]
        if not self.beam:
            return [self._reply(p.START_MEASUREMENT, p.MEAS_STATUS_NOT_READY_ERROR)]
        delay = self.settings.measure_ms / 1000.0 * self.time_scale
        self.busy_until = now + delay
        self.measurements += 1
        every = self.faults.beam_break_every
        if every and self.measurements % every == 0:
            self.beam = False
            self.restore_at = now + delay + self.faults.beam_restore_s
            self._at(delay, p.encode_error(p.START_MEASUREMENT, p.NO_STATIONARY_RESULT), now)
            for data in self._event(p.MEAS_NOT_READY):
                self._at(delay, data, now)
        else:
            self._at(delay, self._result(), now)
        return [self._reply(p.START_MEASUREMENT, p.OK)]

    def _relock(self) -> list[bytes]:
        """The beam is back: "ready" when it was not."""
        was = self.beam
        self.beam = True
        self.restore_at = None
        return [] if was else self._event(p.MEAS_READY)

    def _set(self, command: int, args: tuple[Any, ...], now: float) -> list[bytes]:
        s = self.settings
        if command == p.SET_UNITS:
            length, angle, temperature, pressure, humidity = (int(a) for a in args)
            units = (length, angle, temperature, pressure, humidity)
            known = units[0] in LENGTH_MM and units[1] in (0, 1, 2)
            known &= units[2] in TEMPERATURE and units[3] in PRESSURE_HPA and units[4] == 0
            if not known:
                return [self._reply(command, p.WRONG_PARAMETER)]
            s.units = units
        elif command == p.SET_ENVIRONMENT_PARAMS:
            env = self._from_units(*(float(a) for a in args))
            ranges = (T_RANGE, P_RANGE, RH_RANGE)
            if not all(lo <= v <= hi for v, (lo, hi) in zip(env, ranges, strict=True)):
                return [self._reply(command, p.METEO_OUT_OF_RANGE)]
            s.environment = env
        elif command == p.SET_MEASUREMENT_MODE:
            s.mode = int(args[0])
        elif command == p.SET_COORDINATE_SYSTEM_TYPE:
            s.coordinates = int(args[0])
        elif command == p.SET_STATIONARY_MODE_PARAMS:
            s.measure_ms, s.use_adm = (int(a) for a in args)
        elif command == p.SET_REFLECTOR:
            if int(args[0]) not in {r[0] for r in REFLECTORS}:
                return [self._reply(command, p.WRONG_PARAMETER)]
            s.reflector = int(args[0])
        elif command == p.SET_SYSTEM_SETTINGS:
            s.system = tuple(int(a) for a in args)
        elif command == p.SET_STATISTIC_MODE:
            s.statistic = (int(args[0]), int(args[1]))
        return [self._reply(command, p.OK)]

    # -- values

    def _length(self) -> float:
        """mm per length unit set."""
        return LENGTH_MM[self.settings.units[0]]

    def _air(self) -> tuple[float, float, float]:
        """°C, hPa, %RH the tracker uses: its station's reading, or what it was told."""
        station = self.meteo_station and self.settings.system[0] != p.WEATHER_NOT_CONNECTED
        return self.air if station else self.settings.environment

    def _to_units(self, t: float, pr: float, rh: float) -> tuple[float, float, float]:
        a, b = TEMPERATURE[self.settings.units[2]]
        return t * a + b, pr / PRESSURE_HPA[self.settings.units[3]], rh

    def _from_units(self, t: float, pr: float, rh: float) -> tuple[float, float, float]:
        a, b = TEMPERATURE[self.settings.units[2]]
        return (t - b) / a, pr * PRESSURE_HPA[self.settings.units[3]], rh

    def _result(self) -> bytes:
        k = 1.0 / self._length()
        xyz = self.sample() * k
        cov = self.covariance() * k * k
        std = np.sqrt(np.diag(cov))
        extended = self.settings.statistic[0] == p.STATISTIC_EXTENDED
        covar = (float(cov[0, 1]), float(cov[0, 2]), float(cov[1, 2])) if extended else None
        m = p.Measurement(
            p.OK,
            (float(xyz[0]), float(xyz[1]), float(xyz[2])),
            (float(std[0]), float(std[1]), float(std[2])),
            covar,
            *self._to_units(*self._air()),
        )
        return p.encode_measurement(m)

    def _get(self, command: int, now: float) -> tuple[Any, ...]:
        s = self.settings
        if command == p.GET_SYSTEM_STATUS:
            processor = p.TRACKER_PROCESSOR_INITIALIZED if self.initialized else 3
            laser = p.LASER_READY if self.warm(now) else 2
            status = (self.last_status, processor, laser, p.ADM_READY, *FIRMWARE)
            return (*status, s.system[0], 0, SERIAL)
        if command == p.GET_UNITS:
            return s.units
        if command == p.GET_ENVIRONMENT_PARAMS:
            return self._to_units(*self._air())
        if command == p.GET_REFLECTOR:
            return (s.reflector,)
        if command == p.GET_SYSTEM_SETTINGS:
            return s.system
        if command == p.GET_STATISTIC_MODE:
            return s.statistic
        if command == p.GET_MEASUREMENT_STATUS_INFO:
            flags = p.IN_FACE1 | (p.INITIALIZED if self.initialized else 0)
            flags |= p.REFLECTOR_FOUND if self.beam else 0
            return (self.last_status, flags)
        if command == p.GET_TRACKER_INFO:
            k = 1.0 / self._length()
            name = p.encode_name("AT401")
            return (70, name, SERIAL, 1, 1, 0, 1, 0.0, 160000 * k, 0.0, 1000, 2, 0.0, 0.0, 1, 1, 0)
        if command == p.GET_METEO_STATION_INFO:
            kind = 2 if self.meteo_station else 0
            return (kind, p.encode_name("AT meteo" if self.meteo_station else ""), 1, 0)
        return ()


def _searching(state: EmsconState, command: int, now: float) -> list[bytes]:
    """FindReflector, GoBirdBath: the beam is back (after a search of no time)."""
    return [state._reply(command, p.OK), *state._relock()]


def _get_reflectors(state: EmsconState, args: tuple[Any, ...], now: float) -> list[bytes]:
    n = len(REFLECTORS)
    return [
        state._reply(p.GET_REFLECTORS, p.OK, n, rid, kind, offset, p.encode_name(name))
        for rid, name, kind, offset in REFLECTORS
    ]


def _setter(command: int) -> Callable[[EmsconState, tuple[Any, ...], float], list[bytes]]:
    return lambda state, args, now: state._set(command, args, now)


def _action(command: int) -> Callable[[EmsconState, tuple[Any, ...], float], list[bytes]]:
    return lambda state, args, now: _searching(state, command, now)


_HANDLERS: dict[int, Callable[[EmsconState, tuple[Any, ...], float], list[bytes]]] = {
    p.INITIALIZE: EmsconState._initialize,
    p.START_MEASUREMENT: EmsconState._start,
    p.GET_REFLECTORS: _get_reflectors,
    p.STOP_MEASUREMENT: lambda state, args, now: [state._reply(p.STOP_MEASUREMENT, p.OK)],
    p.FIND_REFLECTOR: _action(p.FIND_REFLECTOR),
    p.GO_BIRD_BATH: _action(p.GO_BIRD_BATH),
    **{
        c: _setter(c)
        for c in (
            p.SET_UNITS,
            p.SET_ENVIRONMENT_PARAMS,
            p.SET_MEASUREMENT_MODE,
            p.SET_COORDINATE_SYSTEM_TYPE,
            p.SET_STATIONARY_MODE_PARAMS,
            p.SET_REFLECTOR,
            p.SET_SYSTEM_SETTINGS,
            p.SET_STATISTIC_MODE,
        )
    },
}
