"""The tracker twin's side of one connection: the codec of tracker line protocol
versions 1 and 2 (``docs/tracker.md``: framing, request parsing, replies) and
``TrackerSession``, which reads the request lines of one link, answers them, streams a
series and keeps the fault cadences of that connection. The tracker state the sessions
share is ``TrackerTwin`` (``tracker_server``); the link and its thread come from
``link_server``.

A session is one select loop (its link's ``wait``) that reads requests and streams points,
so a ``STOP`` is heard while a series streams.

Choices where the spec leaves room (the protocol spec is the contract; these fill gaps):

* A request line is at most 256 bytes, not counting ``\\n`` and one ``\\r`` before it; a
  longer one is dropped as it comes (never held whole), said in a log line and answered
  ``ERR 3`` when it ends.
* Lines that are empty or only ASCII whitespace are ignored (no reply). Commands are
  case-sensitive. Tokens are separated by ASCII whitespace.
* A line whose first word is not a request gets ``ERR 4 UNKNOWN_COMMAND``; a known
  request with a wrong argument (or a byte that is not printable ASCII) gets
  ``ERR 3 BAD_PARAMETER``; a query given an argument gets ``ERR 3 BAD_PARAMETER``.
* ``MEAS`` checks, in order: a series running (``ERR 1 BUSY``), the arguments
  (``ERR 3``; the rate is a decimal number, 0.001 to 1000 Hz), ``INIT`` done (``ERR 39``),
  the beam (``ERR 40``). If the target source fails or returns anything but n finite
  rows of 3 (in version 2: or no finite 3×3 covariance), the answer is
  ``ERR 38 NO_TRACKER``.
* The tracker clock advances 1/rate *before* each point, so with ``clock_start`` 12.0 and
  10 Hz the first point is at 12.100 (as in the spec's example); it only moves with points.
* Requests that arrive while a series streams are answered at once, between ``PT``
  lines: ``MEAS`` and ``INIT`` get ``ERR 1 BUSY``, ``STOP`` gets ``OK`` and then the
  series ends with ``END <k>``.
* Beam break: after ``beam_break_after`` points, ``EVT BEAM LOST`` then
  ``ERR 40 BEAM_BROKEN``; a series with n <= ``beam_break_after`` completes and the break
  stays pending.
* Every connection starts in version 1. ``PROTO?`` answers the versions the twin speaks
  (``OK 1,2``; a twin of version 1 alone answers ``PROTO?`` and ``PROTO`` ``ERR 4``);
  ``PROTO <v>`` switches this connection (``ERR 1 BUSY`` while its series runs,
  ``ERR 3`` for a version it does not speak). In version 2 each ``PT`` line adds the
  covariance of the simulated noise where the target is (the same for the points of a
  series: the target does not move), ``%.6g`` each, and the environment the tracker
  holds when the point is sent (``T`` and ``P`` with two decimals, ``RH`` with one).
* Fault cadences count the protocol lines (and replies) of one connection; garbage lines
  are not counted. After ``drop_after_lines`` lines the session raises ``DropLinkError``
  (what a drop does to a TCP connection or a pty: ``link_server``).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cellcal.mocks.link_server import POLL_S, DropLinkError, Link, LinkClosedError

if TYPE_CHECKING:
    from cellcal.mocks.tracker.server import TrackerTwin

log = logging.getLogger("cellcal.mocks.tracker")

MAX_LINE = 256
REFLECTORS = ("RRR15", "RRR05", "RRR0875", "TBR05")
MAX_POINTS = 10000
MIN_RATE_HZ = 0.001
MAX_RATE_HZ = 1000.0
DEFAULT_RATE_HZ = 10.0
T_RANGE = (0.0, 40.0)
P_RANGE = (600.0, 1100.0)
RH_RANGE = (0.0, 95.0)

BUSY = "ERR 1 BUSY"
BAD_PARAMETER = "ERR 3 BAD_PARAMETER"
LINE_TOO_LONG = "ERR 3 BAD_PARAMETER line too long"
UNKNOWN_COMMAND = "ERR 4 UNKNOWN_COMMAND"
NO_TRACKER = "ERR 38 NO_TRACKER"
NOT_INITIALIZED = "ERR 39 NOT_INITIALIZED"
BEAM_BROKEN = "ERR 40 BEAM_BROKEN"
METEO_OUT_OF_RANGE = "ERR 57 METEO_OUT_OF_RANGE"

_COMMANDS = frozenset(
    {b"*IDN?", b"INIT", b"STAT?", b"ENV?", b"ENV", b"SMR", b"SMR?", b"MEAS", b"STOP"}
)
_VERSION_2 = frozenset({b"PROTO?", b"PROTO"})
#: The upper triangle of a 3×3 covariance, row by row: xx xy xz yy yz zz.
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_PRINTABLE = re.compile(rb"[\x20-\x7e\t]*")
_INT = re.compile(rb"[0-9]+")
_NUMBER = re.compile(rb"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_MAX_COORD = 1e12  # keeps a PT line far below 256 bytes
_BATCH = 256  # points streamed between two looks at the input when time_scale is 0


def _fmt(value: float) -> str:
    """A plain decimal with at least one digit after the point (20.0, 1013.25)."""
    text = f"{value + 0.0:.6f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


def _environment(args: list[bytes]) -> tuple[float, float, float] | str:
    """The (T, P, RH) of an ``ENV`` request, or its error reply."""
    values: dict[bytes, float] = {}
    for arg in args:
        key, eq, text = arg.partition(b"=")
        if not eq or key not in (b"T", b"P", b"RH") or key in values:
            return BAD_PARAMETER
        if not _NUMBER.fullmatch(text):
            return BAD_PARAMETER
        value = float(text)
        if not math.isfinite(value):
            return BAD_PARAMETER
        values[key] = value
    if len(values) != 3:
        return BAD_PARAMETER
    T, P, RH = values[b"T"], values[b"P"], values[b"RH"]
    for v, (lo, hi) in ((T, T_RANGE), (P, P_RANGE), (RH, RH_RANGE)):
        if not lo <= v <= hi:
            return METEO_OUT_OF_RANGE
    return T, P, RH


@dataclass
class _Series:
    n: int
    rate: float
    xyz: np.ndarray
    t0: float  # tracker clock at the start
    interval_s: float  # wall seconds between points
    start_wall: float
    break_at: int | None
    cov: str = ""  # version 2: the six covariance terms of every point, formatted
    sent: int = 0


class TrackerSession:
    """One connection: reads request lines, answers them, streams a series."""

    def __init__(self, tracker: TrackerTwin, link: Link) -> None:
        self.tracker = tracker
        self.faults = tracker.faults
        self.link = link
        self.inbuf = bytearray()
        self.discarding = False
        self.out = bytearray()
        self.lines_sent = 0
        self.replies = 0
        self.series: _Series | None = None
        self.pending_events: deque[str] = deque()
        self.version = 1  # every connection starts in version 1

    # -- loop

    def run(self) -> None:
        """Serve until the client closes (returns) or a fault drops the link
        (DropLinkError)."""
        stop = self.link.stop
        if self.faults.drop_after_lines == 0:
            raise DropLinkError
        while not stop.is_set():
            if self.link.wait(self._timeout()):
                data = self.link.read()
                if data is None:
                    return
                if data:
                    self._feed(data)
            self._tick()
            self._flush()

    def _timeout(self) -> float:
        timeout = POLL_S
        if self.pending_events or self.out:
            return 0.0
        now = time.monotonic()
        if self.series is not None:
            due = self.series.start_wall + self.series.sent * self.series.interval_s
            timeout = min(timeout, due - now)
        restore = self.tracker._beam_restore_due()
        if restore is not None:
            timeout = min(timeout, restore - now)
        return max(0.0, timeout)

    def _tick(self) -> None:
        self.tracker._poll_beam()
        while self.pending_events:
            self._event(self.pending_events.popleft())
        self._stream()

    def _flush(self) -> None:
        if self.out:
            data = bytes(self.out)
            self.out.clear()
            self.link.write(data)

    # -- output

    def _emit(self, line: str) -> None:
        every = self.faults.garbage_every
        if every and (self.lines_sent + 1) % every == 0:
            self.out += self.tracker._garbage() + b"\n"
        self.out += line.encode("ascii") + b"\n"
        self.lines_sent += 1
        drop = self.faults.drop_after_lines
        if drop is not None and self.lines_sent >= drop:
            self._flush()
            raise DropLinkError

    def _event(self, line: str) -> None:
        self.tracker._count_event()
        self._emit(line)

    def _reply(self, line: str) -> None:
        """The answer to one request (its first line)."""
        delay = self.faults.reply_delay_s
        if delay > 0:
            self._flush()
            if self.link.stop.wait(delay):
                raise LinkClosedError
        self.replies += 1
        every = self.faults.event_every
        if every and self.replies % every == 0:
            self._event(f"EVT TEMP {self.tracker._temperature_reading()}")
        self._emit(line)

    # -- input

    def _feed(self, data: bytes) -> None:
        self.inbuf += data
        while True:
            nl = self.inbuf.find(b"\n")
            if nl < 0:
                if len(self.inbuf) > MAX_LINE + 1:  # room for a "\r" before the "\n"
                    if not self.discarding:
                        self.tracker._record(bytes(self.inbuf[:MAX_LINE]))
                        self._overlong()
                    self.discarding = True
                    self.inbuf.clear()
                return
            raw = bytes(self.inbuf[:nl])
            del self.inbuf[: nl + 1]
            if self.discarding:
                self.discarding = False
                self._reply(LINE_TOO_LONG)
                continue
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if len(raw) > MAX_LINE:
                self.tracker._record(raw[:MAX_LINE])
                self._overlong()
                self._reply(LINE_TOO_LONG)
                continue
            self._request(raw)

    def _overlong(self) -> None:
        log.warning(
            "tracker twin: a request line longer than %d bytes: dropped (ERR 3 when it ends)",
            MAX_LINE,
        )

    def _request(self, raw: bytes) -> None:
        tokens = raw.split()
        if not tokens:
            return
        self.tracker._record(raw)
        cmd, args = tokens[0], tokens[1:]
        if cmd not in _COMMANDS and (cmd not in _VERSION_2 or 2 not in self.tracker.versions):
            self._reply(UNKNOWN_COMMAND)
            return
        if not _PRINTABLE.fullmatch(raw):
            self._reply(BAD_PARAMETER)
            return
        try:
            answer = self._answer(cmd, args)
        except (LinkClosedError, DropLinkError):
            raise
        except Exception:
            log.exception("tracker twin: request %r failed", raw)
            answer = f"{NO_TRACKER} internal error"
        self._reply(answer)
        if cmd == b"MEAS" and answer.startswith("OK"):
            self._stream()  # with time_scale 0 the points follow at once
        elif cmd == b"STOP" and answer == "OK" and self.series is not None:
            self._end_series(f"END {self.series.sent}")

    def _answer(self, cmd: bytes, args: list[bytes]) -> str:
        t = self.tracker
        if cmd == b"MEAS":
            return self._start_series(args)
        if cmd == b"ENV":
            env = _environment(args)
            if isinstance(env, str):
                return env
            t._set_environment(env)
            return "OK"
        if cmd == b"PROTO":
            return self._protocol(args)
        if cmd == b"SMR":
            if len(args) != 1 or args[0].decode() not in REFLECTORS:
                return BAD_PARAMETER
            t._set_reflector(args[0].decode())
            return "OK"
        if args:
            return BAD_PARAMETER
        if cmd == b"*IDN?":
            return f"OK {t._identity()}"
        if cmd == b"INIT":
            return t._initialise()
        if cmd == b"STAT?":
            return t._status()
        if cmd == b"ENV?":
            T, P, RH = t._environment()
            return f"OK T={_fmt(T)} P={_fmt(P)} RH={_fmt(RH)}"
        if cmd == b"SMR?":
            return f"OK {t._reflector()}"
        if cmd == b"PROTO?":
            return "OK " + ",".join(map(str, t.versions))
        return "OK"  # STOP; the series, if any, is ended after the reply

    def _protocol(self, args: list[bytes]) -> str:
        """``PROTO <v>``: this connection speaks version v from the next line on."""
        if self.series is not None:
            return BUSY
        if (
            len(args) != 1
            or not _INT.fullmatch(args[0])
            or int(args[0]) not in self.tracker.versions
        ):
            return BAD_PARAMETER
        self.version = int(args[0])
        return f"OK {self.version}"

    # -- series

    def _start_series(self, args: list[bytes]) -> str:
        t = self.tracker
        if t._busy():
            return BUSY
        if not 1 <= len(args) <= 2 or not _INT.fullmatch(args[0]):
            return BAD_PARAMETER
        n = int(args[0])
        rate = DEFAULT_RATE_HZ
        if len(args) == 2:
            if not _NUMBER.fullmatch(args[1]):
                return BAD_PARAMETER
            rate = float(args[1])
        if not (1 <= n <= MAX_POINTS and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
            return BAD_PARAMETER
        refused = t._claim(self)
        if refused is not None:
            return refused
        c = np.zeros((3, 3))
        try:
            xyz = np.array(t.source.sample(n), dtype=np.float64)
            if self.version == 2:
                c = np.array(t._covariance(), dtype=np.float64)
        except Exception:
            log.exception("mock tracker: target source failed")
            xyz = np.empty((0, 3))
        if (
            xyz.shape != (n, 3)
            or not bool(np.all(np.abs(xyz) < _MAX_COORD))
            or c.shape != (3, 3)
            or not bool(np.all(np.isfinite(c)))
        ):
            t._release(self)
            return f"{NO_TRACKER} target source failed"
        t0, break_at = t._series_start(n)
        cov = "".join(f" {c[i, j]:.6g}" for i, j in _UPPER) if self.version == 2 else ""
        self.series = _Series(
            n=n,
            rate=rate,
            xyz=xyz,
            t0=t0,
            interval_s=t.time_scale / rate,
            start_wall=time.monotonic(),
            break_at=break_at,
            cov=cov,
        )
        return f"OK {n}"

    def _stream(self) -> None:
        s = self.series
        if s is None:
            return
        t = self.tracker
        now = time.monotonic()
        budget = _BATCH
        while self.series is s and budget > 0:
            if s.sent < s.n and now < s.start_wall + s.sent * s.interval_s:
                return
            if s.sent == s.break_at:
                t._break_beam()
                self._event("EVT BEAM LOST")
                self._end_series(BEAM_BROKEN)
                return
            if s.sent == s.n:
                self._end_series(f"END {s.n}")
                return
            i = s.sent
            tp = s.t0 + (i + 1) / s.rate
            x, y, z = s.xyz[i]
            t._set_clock(tp)
            s.sent += 1
            line = f"PT {i} {tp:.3f} {x:.4f} {y:.4f} {z:.4f}"
            if s.cov:
                T, P, RH = t._environment()
                line += f"{s.cov} {T:.2f} {P:.2f} {RH:.1f}"
            self._emit(line)
            budget -= 1

    def _end_series(self, last: str) -> None:
        self.series = None
        self.tracker._release(self)
        self._emit(last)
