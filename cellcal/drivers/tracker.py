"""(Size: about 540 lines — one module per device family holds the family's options, driver
and describe(); its protocol and framing are apart in tracker_protocol.py and
line_framing.py.)

A laser tracker that speaks cellcal's tracker line protocol, over any pyserial URL.

Layers, each replaceable without touching the others: transport (bytes; serial, pty,
TCP) → line framing → protocol (requests, replies, events, error codes as exceptions;
``tracker_protocol``) → this vendor-neutral API: identify, initialise, environment,
reflector, status, and ``measure(n, rate)`` returning samples with device and host
timestamps — in line protocol version 2 (``tracker_versions``) each with its
covariance and the air the tracker compensated it with. A second dialect (Leica emScon,
binary on TCP 700) would be another class with the same API over the same transport.

Faults, and what the driver does about them:

* every request has a timeout; no answer → reconnect and retry once, then an error;
* garbled or unexpected lines are counted (``garbage``) and logged, never taken for
  data (a banner or noise before an answer is skipped); ``EVT`` lines are recorded
  (``events``) wherever they appear. A device that sends more than ``JUNK_LIMIT``
  bytes that are not the protocol in one wait, or no answer but such bytes, talks but
  not the protocol: one :class:`TrackerProtocolError` line saying how many bytes and
  their first ones, never "unreachable"; so is a series that does not end in time;
* a series of ``n`` points is re-taken until it has ``n``, in at most ``2 n`` attempts
  (a point kept, or one that failed: a break, a garbled point, a lost link, a series
  cut short): the points before a fault are kept and the rest asked for again. After
  ``BEAM_BROKEN`` the driver first waits for the beam (``EVT BEAM OK`` or ``STAT?``);
  the break after ``beam_retries`` of them ends the series. An empty series (``END 0``,
  no STOP asked for) ends the re-takes: the tracker answers but does not measure. A
  series still short is returned with what it has and a note saying why (the campaign
  stores it with a ``short-series`` event); with no point at all, a broken beam is a
  :class:`BeamBrokenError` (the pose is kept without the tracker), an empty series one
  :class:`TrackerError` line;
* a dropped connection or an unplugged device: reconnect with exponential backoff
  (``reconnects`` attempts), repeat the handshake, carry on; points already received
  are kept.
"""

from __future__ import annotations

import logging
import time
from typing import Annotated, Literal

from pydantic import Field

from cellcal.clock import Clock, WallClock
from cellcal.device_options import SensorOptions
from cellcal.drivers.base import DeviceContext, DeviceDescription, Series, label, naming_errors
from cellcal.drivers.line_framing import Line, LineReader
from cellcal.drivers.tracker_protocol import (
    BeamBrokenError,
    End,
    Environment,
    Err,
    Evt,
    Garbage,
    Junk,
    Message,
    Ok,
    Point,
    TrackerBadParameterError,
    TrackerError,
    TrackerIdentity,
    TrackerProtocolError,
    TrackerSilentError,
    TrackerStatus,
    TrackerTimeoutError,
    error_for,
    parse_line,
)
from cellcal.drivers.tracker_versions import Received, negotiate
from cellcal.drivers.transport import SerialUrlTransport, Transport, TransportError
from cellcal.errors import DeviceError

__all__ = ["Environment", "LineTracker", "LineTrackerOptions", "TrackerIdentity", "TrackerStatus"]

log = logging.getLogger("cellcal.tracker")

REFLECTORS = ("RRR15", "RRR05", "RRR0875", "TBR05")
#: Bytes that are not the protocol, in one wait for an answer or one series, past which
#: the device is said to talk something else (a banner or noise before are skipped).
JUNK_LIMIT = 65536


def request_of(n: int, rate_hz: float) -> str:
    """The request of a series of ``n`` points at ``rate_hz``."""
    return f"MEAS {n} {rate_hz:g}"


def _fields(payload: str) -> dict[str, str]:
    return dict(kv.split("=", 1) for kv in payload.split() if "=" in kv)


class LineTrackerOptions(SensorOptions):
    """A ``[[sensor]]`` with ``kind = "laser-tracker"``, ``driver = "line-protocol"``:
    ``address`` is a pyserial URL (``/dev/ttyUSB0``, a pty path, ``socket://host:port``);
    a reply later than ``timeout_s`` is a fault; a broken beam is waited for up to
    ``beam_wait_s`` and a series re-measured up to ``beam_retries`` times; a lost link is
    reopened up to ``reconnects`` times; ``reflector`` (RRR15, RRR05, RRR0875, TBR05)
    is set at connect when given; ``protocol`` is the line protocol's version (1, or 2:
    each sample's covariance and air), by default the highest the tracker announces."""

    kind: Literal["laser-tracker"] = "laser-tracker"
    driver: Literal["line-protocol"] = "line-protocol"
    timeout_s: Annotated[float, Field(gt=0, le=600)] = 5.0
    beam_retries: Annotated[int, Field(ge=0, le=100)] = 3
    beam_wait_s: Annotated[float, Field(ge=0, le=3600)] = 30.0
    reconnects: Annotated[int, Field(ge=0, le=100)] = 5
    reflector: Literal["RRR15", "RRR05", "RRR0875", "TBR05"] | None = None
    protocol: Literal[1, 2] | None = None


class LineTracker:
    """A tracker at ``address``; implements the engine's PositionSensor Protocol. Every
    DeviceError of its public calls names it (``device``: its name), the link's too.
    ``protocol``: the version to speak, 1 (asks nothing: the default here), 2, or None
    for the highest the tracker announces (the configuration's default); ``version``:
    the one the connection speaks."""

    def __init__(
        self,
        name: str,
        address: str,
        *,
        clock: Clock | None = None,
        transport: Transport | None = None,
        timeout: float = 5.0,
        beam_retries: int = 3,
        beam_wait_s: float = 30.0,
        reconnects: int = 5,
        backoff_s: float = 0.1,
        reflector: str | None = None,
        environment: Environment | None = None,
        protocol: int | None = 1,
    ) -> None:
        self.name = name
        # "tracker t1", but not "tracker tracker" when the sensor is called so.
        self.label = name if "tracker" in name.lower() else f"tracker {name}"
        self.address = address
        self.where = label(self.label, address)
        self.clock = clock or WallClock()
        self.transport = transport or SerialUrlTransport(address)
        self.lines = LineReader(self.transport)
        self.timeout = timeout
        self.beam_retries = beam_retries
        self.beam_wait_s = beam_wait_s
        self.reconnects = reconnects
        self.backoff_s = backoff_s
        self.reflector_type = reflector
        self.env = environment
        self.protocol, self.version = protocol, 1
        self.identity: TrackerIdentity | None = None
        self.events: list[tuple[float, Evt]] = []
        self.garbage = 0
        self.retries = 0
        self.reconnections = 0

    @classmethod
    def from_options(cls, options: LineTrackerOptions, context: DeviceContext) -> LineTracker:
        return cls(
            options.name,
            options.address,
            clock=context.clock,
            timeout=options.timeout_s,
            beam_retries=options.beam_retries,
            beam_wait_s=options.beam_wait_s,
            reconnects=options.reconnects,
            reflector=options.reflector,
            protocol=options.protocol,
        )

    # ------------------------------------------------------------------ connection

    @naming_errors
    def connect(self) -> None:
        """Open the link, identify and initialise the tracker (and set reflector and
        environment if configured)."""
        self._open_with_backoff()
        try:
            try:
                self._handshake()
            except TrackerSilentError as exc:
                self._silent_at_connect(exc)
            except TransportError as exc:
                self._reconnect(exc)
        except BaseException:
            self.transport.close()
            raise

    def _silent_at_connect(self, why: TrackerSilentError) -> None:
        """The link opened but nothing answered the handshake: open it again and ask once
        more (docs/tracker.md: retry once); silent again, it is not "unreachable" (the
        link is up) but one line saying that nothing there speaks the protocol."""
        self.reconnections += 1
        log.warning("%s: %s; opening the link again", self.label, why)
        self.transport.close()
        time.sleep(self.backoff_s)
        try:
            self.transport.open()
            self.lines.reset()
            self._handshake()
        except TrackerSilentError as exc:
            raise TrackerTimeoutError(
                f"{exc}, twice, with the link open: is it a tracker or bridge that speaks "
                "the line protocol? (`cellcal tracker --conformance` tells more)"
            ) from None
        except TransportError as exc:
            self._reconnect(exc)

    def close(self) -> None:
        self.transport.close()

    def _open_with_backoff(self) -> None:
        delay = self.backoff_s
        for attempt in range(1, self.reconnects + 2):
            try:
                self.transport.open()
                self.lines.reset()
                return
            except TransportError as exc:
                if attempt > self.reconnects:
                    raise TransportError(
                        f"{self.where}: unreachable after {attempt} attempts ({exc})"
                    ) from None
                log.warning("%s: %s; retrying in %.2f s", self.label, exc, delay)
                time.sleep(delay)
                delay = min(delay * 2, 5.0)

    def _handshake(self) -> None:
        self.identity = self._identify(retry=False)
        self.version = negotiate(lambda r: self._request(r, retry=False), self.protocol, self.where)
        self._request("INIT", timeout=max(self.timeout, 60.0), retry=False)
        if self.reflector_type is not None:
            self._request(f"SMR {self.reflector_type}", retry=False)
        if self.env is not None:
            self._request(self._env_request(self.env), retry=False)

    def _reconnect(self, why: Exception) -> None:
        """Close, wait, reopen and repeat the handshake, with exponential backoff;
        ``reconnects`` attempts, then one clear error."""
        delay = self.backoff_s
        last: Exception = why
        for attempt in range(1, self.reconnects + 1):
            self.reconnections += 1
            log.warning("%s: %s; reconnecting (%d)", self.label, last, attempt)
            self.transport.close()
            time.sleep(delay)
            delay = min(delay * 2, 5.0)
            try:
                self.transport.open()
                self.lines.reset()
                self._handshake()
                return
            except (TransportError, TrackerSilentError) as exc:
                last = exc
        raise TransportError(
            f"{self.where}: unreachable after {self.reconnects} reconnection attempts ({last})"
        )

    # ------------------------------------------------------------------ requests

    def _note(self, msg: Evt | Garbage | Point | End | Ok | Err, context: str) -> None:
        if isinstance(msg, Evt):
            self.events.append((self.clock.now(), msg))
            log.info("%s: event %s %s", self.label, msg.name, msg.payload)
        else:
            self.garbage += 1
            log.warning("%s: ignored %r while %s", self.label, msg, context)

    def _junk(self, junk: Junk, line: Line, msg: Message, waiting: str) -> None:
        """Count a line that is not the protocol; past :data:`JUNK_LIMIT` bytes of them
        in one wait, the device talks but not the protocol: say so, with what it sent."""
        if isinstance(msg, Garbage):
            junk.add(line.raw, line.size)
            if junk.size > JUNK_LIMIT:
                raise junk.error(self.where, waiting)

    def _timed_out(self, junk: Junk, waiting: str, silence: str, timeout: float) -> DeviceError:
        """The error of a wait that ended without its answer: a device that sent what is
        not the protocol (an unfinished line longer than a line included) is said to;
        else a timeout (a link that stalls, even within a line)."""
        pending = self.lines.pending
        if junk.size or pending > self.lines.max_line:
            return junk.error(self.where, waiting, pending=pending, head=self.lines.head)
        return TrackerSilentError(f"{self.where}: {silence} within {timeout:g} s")

    def _reply(self, request: str, timeout: float) -> Ok:
        deadline = time.monotonic() + timeout
        junk = Junk()
        waiting = f"waiting for the answer to {request!r}"
        while True:
            line = self.lines.read_line(max(0.0, deadline - time.monotonic()))
            if line is None:
                raise self._timed_out(junk, waiting, f"no answer to {request!r}", timeout)
            msg = parse_line(line.raw) if not line.overlong else Garbage(line.raw, "too long")
            if isinstance(msg, Ok):
                return msg
            if isinstance(msg, Err):
                raise error_for(msg, request, f"{self.label}")
            self._note(msg, waiting)
            self._junk(junk, line, msg, waiting)

    def _request(self, request: str, timeout: float | None = None, *, retry: bool = True) -> Ok:
        """Send one request and return its OK; on a broken link or a timeout reconnect
        and retry once (not inside the handshake of a reconnection)."""
        t = self.timeout if timeout is None else timeout
        try:
            self.lines.write_line(request)
            return self._reply(request, t)
        except (TransportError, TrackerSilentError) as exc:
            if not retry:
                raise
            self._reconnect(exc)
        self.lines.write_line(request)
        return self._reply(request, t)

    @naming_errors
    def identify(self) -> TrackerIdentity:
        return self._identify(retry=True)

    def _identify(self, *, retry: bool) -> TrackerIdentity:
        parts = self._request("*IDN?", retry=retry).payload.split(",")
        if len(parts) != 4:
            raise TrackerError(f"{self.label}: malformed *IDN? answer {','.join(parts)!r}")
        return TrackerIdentity(*(p.strip() for p in parts))

    def describe(self) -> DeviceDescription:
        """The tracker at ``address`` as the handshake's ``*IDN?`` told (maker, model,
        serial, firmware; None before it connected): asks the tracker nothing."""
        family = "laser-tracker/line-protocol"
        if (who := self.identity) is None:
            return DeviceDescription(self.name, family, self.address)
        return DeviceDescription(
            self.name, family, self.address, who.maker, who.model, who.firmware, who.serial
        )

    def summary(self) -> str:
        """One line for the campaign's record and its report: the tracker's identity
        and, when it reports them, the air readings it compensates with."""
        who = self.identity
        text = f"{self.where}: " + (
            f"{who.maker} {who.model}, serial {who.serial}, firmware {who.firmware}"
            if who is not None
            else "not identified"
        )
        try:
            env = self.environment()
        except DeviceError as exc:
            log.info("%s: no environment readings (%s)", self.label, exc)
            return text
        return (
            f"{text}; air {env.temperature_c:.2f} °C, {env.pressure_hpa:.2f} hPa, "
            f"{env.humidity_pct:.1f} % RH"
        )

    @naming_errors
    def initialise(self) -> None:
        self._request("INIT", timeout=max(self.timeout, 60.0))

    @naming_errors
    def status(self) -> TrackerStatus:
        f = _fields(self._request("STAT?").payload)
        try:
            return TrackerStatus(*(f[k] == "1" for k in ("ready", "beam", "meteo", "init")))
        except KeyError as exc:
            raise TrackerError(f"{self.label}: STAT? answer lacks {exc}") from None

    @naming_errors
    def environment(self) -> Environment:
        f = _fields(self._request("ENV?").payload)
        try:
            return Environment(float(f["T"]), float(f["P"]), float(f["RH"]))
        except (KeyError, ValueError) as exc:
            raise TrackerError(f"{self.label}: malformed ENV? answer ({exc})") from None

    @staticmethod
    def _env_request(env: Environment) -> str:
        return f"ENV T={env.temperature_c:.2f} P={env.pressure_hpa:.2f} RH={env.humidity_pct:.1f}"

    @naming_errors
    def set_environment(self, env: Environment) -> None:
        self._request(self._env_request(env))
        self.env = env

    @naming_errors
    def reflector(self) -> str:
        return self._request("SMR?").payload.strip()

    @naming_errors
    def set_reflector(self, kind: str) -> None:
        if kind not in REFLECTORS:
            raise TrackerBadParameterError(f"reflector {kind!r}: one of {', '.join(REFLECTORS)}")
        self._request(f"SMR {kind}")
        self.reflector_type = kind

    # ------------------------------------------------------------------ measuring

    def _series(self, k: int, rate_hz: float, got: Received) -> int:
        """One ``MEAS k``: append the points received to ``got``; return how many the
        tracker says it took (``END c``: fewer than ``k`` when it was stopped, more than
        were received when some came garbled); raises BeamBrokenError after keeping the
        points before the break."""
        request = request_of(k, rate_hz)
        self.lines.write_line(request)
        ok = self._reply(request, self.timeout)
        if ok.payload.strip() != str(k):
            raise TrackerError(f"{self.label}: {request!r} answered 'OK {ok.payload}'")
        expected = 0
        line_timeout = self.timeout + 2.0 / rate_hz
        # An overall deadline too: a peer that keeps the link alive with events or
        # garbage but never finishes the series must not hold the measurement forever.
        budget = self.timeout + 1.5 * k / rate_hz + 2.0
        deadline = time.monotonic() + budget
        junk, heard = Junk(), 0
        waiting = f"measuring {request!r} ({expected} of {k} points)"
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                if junk.size > 0:
                    raise junk.error(self.where, waiting)
                raise TrackerProtocolError(
                    f"{self.where}: {request!r}: the series was not finished within "
                    f"{budget:.3g} s ({expected} of {k} points received, {heard} other lines: "
                    "the tracker talks but does not measure)"
                )
            line = self.lines.read_line(min(line_timeout, left))
            if line is None:
                if time.monotonic() >= deadline:
                    continue
                stalled = f"series stalled after {expected} of {k} points"
                raise self._timed_out(junk, waiting, stalled, line_timeout)
            msg = parse_line(line.raw) if not line.overlong else Garbage(line.raw, "too long")
            if isinstance(msg, Point) and msg.i == expected and msg.version == self.version:
                got.add(self.clock.now(), msg)
                expected += 1
                waiting = f"measuring {request!r} ({expected} of {k} points)"
            elif isinstance(msg, End):
                if not expected <= msg.count <= k:
                    raise TrackerError(f"{self.label}: END {msg.count} after {expected} points")
                return msg.count
            elif isinstance(msg, Err):
                raise error_for(msg, request, f"{self.label}")
            else:
                heard += 1
                self._note(msg, waiting)
                self._junk(junk, line, msg, waiting)

    def _drain(self, timeout: float) -> None:
        """Read what the tracker sends unasked (events) for up to ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            line = self.lines.read_line(left)
            if line is None:
                return
            self._note(parse_line(line.raw), "waiting")

    def _wait_for_beam(self, since: int) -> None:
        deadline = time.monotonic() + self.beam_wait_s
        while time.monotonic() < deadline:
            if any(e.name == "BEAM" and e.payload.strip() == "OK" for _, e in self.events[since:]):
                return
            if self.status().beam:
                return
            self._drain(0.05)
        raise BeamBrokenError(f"{self.label}: no beam for {self.beam_wait_s:g} s", 40)

    @naming_errors
    def measure(self, n: int, rate_hz: float) -> Series:
        """``n`` points at ``rate_hz``, surviving beam breaks, garbled points and dropped
        links: re-taken until there are ``n``, in at most ``2 n`` attempts (a point kept
        or one that failed: a break, a garbled point, a lost link, a series cut short)."""
        if not 1 <= n <= 10000 or not 0 < rate_hz <= 1000:
            raise TrackerBadParameterError(
                f"measure: n in 1..10000 and rate in (0, 1000] Hz, got {n}, {rate_hz}"
            )
        got = Received()
        failed = breaks = links = series = 0
        problems: list[str] = []
        empty = ""
        while len(got.xyz) < n and len(got.xyz) + failed < 2 * n:
            k = min(n - len(got.xyz), 2 * n - len(got.xyz) - failed)
            before, mark = len(got.xyz), len(self.events)
            series += 1
            try:
                told = self._series(k, rate_hz, got)
            except BeamBrokenError:
                breaks += 1
                failed += 1
                problems.append(f"beam broken after {len(got.xyz) - before} of {k} points")
                if breaks > self.beam_retries:
                    limit = f"beam broken {breaks} times, beam_retries is {self.beam_retries}"
                    problems.insert(0, limit)
                    break
                log.warning("%s: beam broken after %d points; waiting", self.label, len(got.xyz))
                try:
                    self._wait_for_beam(mark)
                except BeamBrokenError as exc:
                    problems.insert(0, str(exc).removeprefix(f"{self.label}: "))
                    break
                continue
            except (TransportError, TrackerSilentError) as exc:
                links += 1
                if links > self.reconnects:
                    raise
                failed += 1
                problems.append(f"link lost after {len(got.xyz) - before} of {k} points")
                self._reconnect(exc)
                continue
            received = len(got.xyz) - before
            if told > received:
                failed += told - received
                problems.append(f"{told - received} of {k} points garbled")
            if told < k:
                failed += 1
                problems.append(f"series ended after {told} of {k} points")
            if told == 0:
                # An empty series (END 0) that no STOP asked for: the tracker answers
                # but does not measure; asking again would get the same, 2 n times.
                empty = f"{request_of(k, rate_hz)!r} answered an empty series (END 0)"
                break
        self.retries += series - 1
        kept = len(got.xyz)
        why = "; ".join(problems[:3]) + ("; …" if len(problems) > 3 else "")
        if kept == 0:
            if empty:
                raise TrackerError(
                    f"{self.label}: {empty}: the tracker answers but does not measure ({why})"
                )
            if breaks:
                raise BeamBrokenError(
                    f"{self.label}: beam broken {breaks} times; 0 of {n} points kept ({why})", 40
                )
            raise TrackerError(f"{self.label}: no point measured in {failed} attempts ({why})")
        note = ""
        if problems:
            note = f"{kept} of {n} samples after {kept + failed} attempts ({failed} failed): {why}"
        return got.series(self.name, retries=series - 1, note=note)
