"""A protocol-level mock laser tracker: tracker line protocol v1
(``docs/tracker.md``) over TCP on a loopback address or over a
pseudo-terminal, so that the real driver runs unchanged against it in CI and in
``cellcal mock tracker``.

Size (about 980 lines): not split yet. Issue 10's remaining part splits it by job (a
reusable TCP/pty link server shared with the UR twin, the protocol codec, the tracker
state) together with the UR twin; splitting it alone first would churn the same lines
twice.

The tracker state (initialised, beam, environment, reflector, its own clock) belongs to
the tracker and outlives a connection; what concerns one link (line counters for the
fault cadences, a running series) belongs to the connection. Every connection is served
by its own thread, one select loop that reads requests and streams points, so a ``STOP``
is heard while a series streams.

Choices where the spec leaves room (the protocol spec is the contract; these fill gaps):

* A request line is at most 256 bytes, not counting ``\\n`` and one ``\\r`` before it.
* Lines that are empty or only ASCII whitespace are ignored (no reply). Commands are
  case-sensitive. Tokens are separated by ASCII whitespace.
* A line whose first word is not a request gets ``ERR 4 UNKNOWN_COMMAND``; a known
  request with a wrong argument (or a byte that is not printable ASCII) gets
  ``ERR 3 BAD_PARAMETER``; a query given an argument gets ``ERR 3 BAD_PARAMETER``.
* ``MEAS`` checks, in order: a series running (``ERR 1 BUSY``), the arguments
  (``ERR 3``; the rate is a decimal number, 0.001 to 1000 Hz), ``INIT`` done (``ERR 39``),
  the beam (``ERR 40``). If the target source fails or returns anything but n finite
  rows of 3, the answer is ``ERR 38 NO_TRACKER``.
* The tracker clock advances 1/rate *before* each point, so with ``clock_start`` 12.0 and
  10 Hz the first point is at 12.100 (as in the spec's example); it only moves with points.
* Requests that arrive while a series streams are answered at once, between ``PT``
  lines: ``MEAS`` and ``INIT`` get ``ERR 1 BUSY``, ``STOP`` gets ``OK`` and then the
  series ends with ``END <k>``.
* ``STAT?``: ``ready`` = initialised and beam and no series running; ``meteo`` = 1 (the
  environment can only hold values within range).
* Beam break: after ``beam_break_after`` points, ``EVT BEAM LOST`` then
  ``ERR 40 BEAM_BROKEN``; a series with n <= ``beam_break_after`` completes and the break
  stays pending. ``EVT BEAM OK`` goes to every connection when the beam is back
  (``beam_restore_s`` later, or at ``INIT``).
* Fault cadences count the protocol lines (and replies) of one connection; garbage lines
  are not counted. ``drop_after_lines`` applies to every connection: after that many
  lines a TCP connection is shut down (FIN), a pty stops answering until the client
  closes and reopens it.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import os
import re
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from cellcal.mocks.twins import TRACKER_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.tracker import LineTrackerOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.tracker")

MAX_LINE = 256
MAKER = "cellcal"
MODEL = "mock-tracker"
FIRMWARE = "1.0"
REFLECTORS = ("RRR15", "RRR05", "RRR0875", "TBR05")
MAX_POINTS = 10000
MIN_RATE_HZ = 0.001
MAX_RATE_HZ = 1000.0
DEFAULT_RATE_HZ = 10.0
T_RANGE = (0.0, 40.0)
P_RANGE = (600.0, 1100.0)
RH_RANGE = (0.0, 95.0)

_POLL_S = 0.05  # the longest a serving loop waits before it looks at the stop flag
_JOIN_S = 2.0
_BATCH = 256  # points streamed between two looks at the input when time_scale is 0
_READ = 65536

_BUSY = "ERR 1 BUSY"
_BAD = "ERR 3 BAD_PARAMETER"
_TOO_LONG = "ERR 3 BAD_PARAMETER line too long"
_UNKNOWN = "ERR 4 UNKNOWN_COMMAND"
_NO_TRACKER = "ERR 38 NO_TRACKER"
_NOT_INIT = "ERR 39 NOT_INITIALIZED"
_BEAM = "ERR 40 BEAM_BROKEN"
_METEO = "ERR 57 METEO_OUT_OF_RANGE"

_COMMANDS = frozenset(
    {b"*IDN?", b"INIT", b"STAT?", b"ENV?", b"ENV", b"SMR", b"SMR?", b"MEAS", b"STOP"}
)
_PRINTABLE = re.compile(rb"[\x20-\x7e\t]*")
_INT = re.compile(rb"[0-9]+")
_NUMBER = re.compile(rb"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_SERIAL = re.compile(r"[\x21-\x7e]+")
_MAX_COORD = 1e12  # keeps a PT line far below 256 bytes


class TargetSource(Protocol):
    def sample(self, n: int) -> np.ndarray:
        """n×3 positions (mm) of the target in the tracker frame, noise included."""
        ...


@dataclass(frozen=True)
class TrackerFaults:
    """Fault injection; everything off by default."""

    beam_break_after: int | None = None
    beam_breaks: int = 1
    beam_restore_s: float = 0.0
    garbage_every: int = 0
    event_every: int = 0
    reply_delay_s: float = 0.0
    drop_after_lines: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("beam_break_after", "drop_after_lines"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ValueError(f"TrackerFaults.{name} must be >= 0 or None, got {value}")
        for name in ("beam_breaks", "garbage_every", "event_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"TrackerFaults.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("beam_restore_s", "reply_delay_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"TrackerFaults.{name} must be finite and >= 0, got {value}")


class _LinkClosedError(Exception):
    """The link is gone (peer closed, error) or the server is stopping."""


class _DropLinkError(Exception):
    """Fault injection: the connection is to be dropped now."""


def _fmt(value: float) -> str:
    """A plain decimal with at least one digit after the point (20.0, 1013.25)."""
    text = f"{value + 0.0:.6f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


# ---------------------------------------------------------------------------- links


class _Link:
    """Bytes to and from one client; ``read`` gives None for nothing yet, b"" for closed."""

    def __init__(self, fd: int, stop: threading.Event) -> None:
        self.fd = fd
        self.stop = stop
        self.poller = select.poll()
        self.poller.register(fd, select.POLLIN)

    def wait(self, timeout: float) -> bool:
        return bool(self.poller.poll(max(0, math.ceil(timeout * 1000))))

    def read(self) -> bytes | None:
        raise NotImplementedError

    def _send(self, data: memoryview) -> int:
        raise NotImplementedError

    def check_open(self) -> None:
        pass

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        out = select.poll()
        out.register(self.fd, select.POLLOUT)
        while view:
            if self.stop.is_set():
                raise _LinkClosedError
            self.check_open()
            try:
                sent = self._send(view)
            except BlockingIOError:
                sent = 0
            except OSError as exc:
                raise _LinkClosedError from exc
            view = view[sent:]
            if view:
                out.poll(int(_POLL_S * 1000))


class _SocketLink(_Link):
    def __init__(self, sock: socket.socket, stop: threading.Event) -> None:
        super().__init__(sock.fileno(), stop)
        self.sock = sock

    def read(self) -> bytes | None:
        try:
            return self.sock.recv(_READ)
        except BlockingIOError:
            return None
        except OSError:
            return b""

    def _send(self, data: memoryview) -> int:
        return self.sock.send(data)


class _PtyLink(_Link):
    """The master side of a pty, and who has its slave open.

    With inotify (Linux) the server keeps the slave open itself, so the master never
    hangs up, and follows the clients' opens and closes of the slave path: a close and
    an immediate reopen are two events, never missed. Elsewhere a client closing shows as
    a hang-up on the master (best effort: a reopen faster than the server looks is seen
    as the same connection).
    """

    def __init__(self, master: int, slave: int, path: str, stop: threading.Event) -> None:
        super().__init__(master, stop)
        self.path = path
        self.watch = _inotify_watch(path)  # after the slave was opened: ours is no event
        self.keeper: int | None = slave
        if self.watch is None:
            os.close(slave)
            self.keeper = None
        else:
            self.poller.register(self.watch, select.POLLIN)
        self.clients = 0
        self.opens = 0
        self.pending: deque[int] = deque()

    def close(self) -> None:
        for fd in (self.watch, self.keeper, self.fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)

    def connected(self) -> bool:
        """Whether the client of the session has the slave open. With inotify, the events
        after the last client's close stay queued: they belong to the next connection."""
        if self.watch is None:
            return not _pty_hung_up(self.fd)
        return self._follow(to_hangup=True)

    def _follow(self, *, to_hangup: bool) -> bool:
        """Count the opens and closes reported so far; whether a client has it open."""
        assert self.watch is not None
        self.pending.extend(_inotify_events(self.watch))
        while self.pending:
            mask = self.pending.popleft()
            if mask & _IN_OPEN:
                self.clients += 1
                self.opens += 1
            elif mask & _IN_CLOSE and self.clients > 0:
                self.clients -= 1
                if self.clients == 0 and to_hangup:
                    return False
        return self.clients > 0

    def wait_open(self, carry: bytes = b"") -> bytes | None:
        """Wait until a client has the slave open. Returns the bytes already read that may
        be its first request (``carry`` included), or None when the server stops."""
        if self.watch is None:
            while not self.stop.is_set():
                if not _pty_hung_up(self.fd):
                    return carry
                self.stop.wait(0.01)
            return None
        return self._wait_for(lambda: self._follow(to_hangup=False), carry)

    def mute_until_reopened(self) -> bytes | None:
        """Read and drop everything until the client closes the slave and opens it again
        (without inotify: until it closes). Returns as ``wait_open`` does."""
        if self.watch is None:
            while not self.stop.is_set():
                if self.wait(_POLL_S) and self.read() == b"":
                    return b""
            return None
        opens = self.opens

        def reopened() -> bool:
            self._follow(to_hangup=False)
            return self.opens > opens

        return self._wait_for(reopened)

    def _wait_for(self, condition: Callable[[], bool], carry: bytes = b"") -> bytes | None:
        """Drop input until ``condition`` holds. An open is reported before the opener can
        write, so bytes read before the condition turned true may be a new client's
        request: those are handed back, not dropped."""
        while not self.stop.is_set():
            if condition():
                return carry
            carry = b""
            if self.wait(_POLL_S):
                with contextlib.suppress(OSError):
                    carry = os.read(self.fd, _READ)
        return None

    def flush_stale(self) -> None:
        """Drop what the server wrote and no client read: a pty keeps unread output for
        the next opener, who must not see replies meant for the last one."""
        fd = self.keeper
        if fd is None:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            except OSError:
                return
        try:
            termios.tcflush(fd, termios.TCIFLUSH)
        except termios.error:
            pass
        finally:
            if fd != self.keeper:
                os.close(fd)

    def read(self) -> bytes | None:
        if not self.connected():
            return b""
        try:
            return os.read(self.fd, _READ)
        except BlockingIOError:
            return None
        except OSError:  # EIO: no client has the slave open
            return b""

    def check_open(self) -> None:
        if not self.connected():
            raise _LinkClosedError

    def _send(self, data: memoryview) -> int:
        return os.write(self.fd, data)


def _pty_hung_up(master: int) -> bool:
    poller = select.poll()
    poller.register(master, select.POLLIN)
    return any(ev & select.POLLHUP for _, ev in poller.poll(0))


_IN_OPEN = 0x20
_IN_CLOSE = 0x08 | 0x10  # IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
_INOTIFY_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)


def _inotify_watch(path: str) -> int | None:
    """An inotify descriptor reporting opens and closes of ``path``, or None where there is
    no inotify."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fd = int(libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC))
    except (OSError, AttributeError):
        return None
    if fd < 0:
        return None
    if libc.inotify_add_watch(fd, os.fsencode(path), _IN_OPEN | _IN_CLOSE) < 0:
        os.close(fd)
        return None
    return fd


def _inotify_events(fd: int) -> list[int]:
    masks: list[int] = []
    while True:
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return masks
        except OSError:
            return masks
        offset = 0
        while offset + _INOTIFY_EVENT.size <= len(data):
            _, mask, _, name_len = _INOTIFY_EVENT.unpack_from(data, offset)
            masks.append(mask)
            offset += _INOTIFY_EVENT.size + name_len


# ---------------------------------------------------------------------------- sessions


@dataclass
class _Series:
    n: int
    rate: float
    xyz: np.ndarray
    t0: float  # tracker clock at the start
    interval_s: float  # wall seconds between points
    start_wall: float
    break_at: int | None
    sent: int = 0


class _Session:
    """One connection: reads request lines, answers them, streams a series."""

    def __init__(self, tracker: MockTracker, link: _Link) -> None:
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

    # -- loop

    def run(self, first: bytes = b"") -> None:
        """Serve until the client closes (returns) or a fault drops the link
        (_DropLinkError); ``first``: bytes from this client read before the session began."""
        stop = self.tracker._stop
        if self.faults.drop_after_lines == 0:
            raise _DropLinkError
        if first:
            self._feed(first)
            self._flush()
        while not stop.is_set():
            if self.link.wait(self._timeout()):
                data = self.link.read()
                if data == b"":
                    return
                if data:
                    self._feed(data)
            self._tick()
            self._flush()

    def _timeout(self) -> float:
        timeout = _POLL_S
        if self.pending_events or self.out:
            return 0.0
        now = time.monotonic()
        if self.series is not None:
            due = self.series.start_wall + self.series.sent * self.series.interval_s
            timeout = min(timeout, due - now)
        restore = self.tracker._restore_at
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
            raise _DropLinkError

    def _event(self, line: str) -> None:
        self.tracker._count_event()
        self._emit(line)

    def _reply(self, line: str) -> None:
        """The answer to one request (its first line)."""
        delay = self.faults.reply_delay_s
        if delay > 0:
            self._flush()
            if self.tracker._stop.wait(delay):
                raise _LinkClosedError
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
                    self.discarding = True
                    self.inbuf.clear()
                return
            raw = bytes(self.inbuf[:nl])
            del self.inbuf[: nl + 1]
            if self.discarding:
                self.discarding = False
                self._reply(_TOO_LONG)
                continue
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if len(raw) > MAX_LINE:
                self.tracker._record(raw[:MAX_LINE])
                self._reply(_TOO_LONG)
                continue
            self._request(raw)

    def _request(self, raw: bytes) -> None:
        tokens = raw.split()
        if not tokens:
            return
        self.tracker._record(raw)
        cmd, args = tokens[0], tokens[1:]
        if cmd not in _COMMANDS:
            self._reply(_UNKNOWN)
            return
        if not _PRINTABLE.fullmatch(raw):
            self._reply(_BAD)
            return
        try:
            answer = self._answer(cmd, args)
        except (_LinkClosedError, _DropLinkError):
            raise
        except Exception:
            log.exception("mock tracker: request %r failed", raw)
            answer = f"{_NO_TRACKER} internal error"
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
            return t._set_environment(args)
        if cmd == b"SMR":
            if len(args) != 1 or args[0].decode() not in REFLECTORS:
                return _BAD
            with t._lock:
                t._smr = args[0].decode()
            return "OK"
        if args:
            return _BAD
        if cmd == b"*IDN?":
            return f"OK {MAKER},{MODEL},{t.serial},{FIRMWARE}"
        if cmd == b"INIT":
            return t._initialise()
        if cmd == b"STAT?":
            return t._status()
        if cmd == b"ENV?":
            with t._lock:
                T, P, RH = t._env
            return f"OK T={_fmt(T)} P={_fmt(P)} RH={_fmt(RH)}"
        if cmd == b"SMR?":
            with t._lock:
                return f"OK {t._smr}"
        return "OK"  # STOP; the series, if any, is ended after the reply

    # -- series

    def _start_series(self, args: list[bytes]) -> str:
        t = self.tracker
        with t._lock:
            if t._owner is not None:
                return _BUSY
        if not 1 <= len(args) <= 2 or not _INT.fullmatch(args[0]):
            return _BAD
        n = int(args[0])
        rate = DEFAULT_RATE_HZ
        if len(args) == 2:
            if not _NUMBER.fullmatch(args[1]):
                return _BAD
            rate = float(args[1])
        if not (1 <= n <= MAX_POINTS and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
            return _BAD
        with t._lock:
            if t._owner is not None:
                return _BUSY
            if not t._initialized:
                return _NOT_INIT
            if not t._beam:
                return _BEAM
            t._owner = self
        try:
            xyz = np.array(t.source.sample(n), dtype=np.float64)
        except Exception:
            log.exception("mock tracker: target source failed")
            xyz = np.empty((0, 3))
        if xyz.shape != (n, 3) or not bool(np.all(np.abs(xyz) < _MAX_COORD)):
            with t._lock:
                t._owner = None
            return f"{_NO_TRACKER} target source failed"
        with t._lock:
            k = t.faults.beam_break_after
            break_at = k if k is not None and t._breaks_left > 0 and k < n else None
            self.series = _Series(
                n=n,
                rate=rate,
                xyz=xyz,
                t0=t._clock,
                interval_s=t.time_scale / rate,
                start_wall=time.monotonic(),
                break_at=break_at,
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
                self._end_series(_BEAM)
                return
            if s.sent == s.n:
                self._end_series(f"END {s.n}")
                return
            i = s.sent
            tp = s.t0 + (i + 1) / s.rate
            x, y, z = s.xyz[i]
            with t._lock:
                t._clock = tp
            s.sent += 1
            self._emit(f"PT {i} {tp:.3f} {x:.4f} {y:.4f} {z:.4f}")
            budget -= 1

    def _end_series(self, last: str) -> None:
        self.series = None
        self.tracker._release(self)
        self._emit(last)


# ---------------------------------------------------------------------------- tracker


class MockTracker:
    """A simulated laser tracker serving the tracker line protocol v1.

    ``time_scale`` 0 streams points as fast as possible; > 0 waits
    (1/rate)·time_scale wall seconds between points.
    """

    def __init__(
        self,
        source: TargetSource,
        *,
        faults: TrackerFaults = TrackerFaults(),
        serial: str = "SIM-0001",
        time_scale: float = 0.0,
        clock_start: float = 12.0,
    ) -> None:
        if not _SERIAL.fullmatch(serial) or "," in serial:
            raise ValueError(f"serial {serial!r}: printable ASCII without spaces or commas")
        if not (math.isfinite(time_scale) and time_scale >= 0):
            raise ValueError(f"time_scale must be finite and >= 0, got {time_scale}")
        if not math.isfinite(clock_start):
            raise ValueError(f"clock_start must be finite, got {clock_start}")
        self.source = source
        self.faults = faults
        self.serial = serial
        self.time_scale = float(time_scale)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._rng = np.random.default_rng(faults.seed)
        self._initialized = False
        self._beam = True
        self._restore_at: float | None = None
        self._breaks_left = faults.beam_breaks if faults.beam_break_after is not None else 0
        self._env = (20.0, 1013.25, 45.0)
        self._smr = REFLECTORS[0]
        self._clock = float(clock_start)
        self._owner: _Session | None = None
        self._sessions: set[_Session] = set()
        self._requests: list[str] = []
        self._events_sent = 0
        self._connections = 0
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._pty_path: str | None = None

    # -- public

    @property
    def events_sent(self) -> int:
        with self._lock:
            return self._events_sent

    @property
    def requests(self) -> list[str]:
        """The request lines received (empty lines not), oldest first; a copy."""
        with self._lock:
            return list(self._requests)

    @property
    def connections(self) -> int:
        """TCP connections accepted plus pty opens seen."""
        with self._lock:
            return self._connections

    def start_tcp(self, host: str = "127.0.0.5", port: int = 0) -> tuple[str, int]:
        """Listen on (host, port) (port 0: any free one) and serve in the background;
        returns the bound address once listening."""
        if self._listener is not None:
            raise RuntimeError("mock tracker: TCP already started")
        if self._stop.is_set():
            raise RuntimeError("mock tracker: stopped")
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((host, port))
            listener.listen(8)
            listener.settimeout(_POLL_S)
        except OSError:
            listener.close()
            raise
        self._listener = listener
        bound = listener.getsockname()
        self._spawn(self._serve_tcp, listener, name=f"mock-tracker-tcp-{bound[1]}")
        return str(bound[0]), int(bound[1])

    def start_pty(self) -> str:
        """Open a pseudo-terminal, serve its master side in the background and return the
        slave's path (open it with pyserial, e.g. ``serial.Serial(path)``)."""
        if self._pty_path is not None:
            raise RuntimeError("mock tracker: pty already started")
        if self._stop.is_set():
            raise RuntimeError("mock tracker: stopped")
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no line discipline: bytes pass untouched
            path = os.ttyname(slave)
            os.set_blocking(master, False)
            link = _PtyLink(master, slave, path, self._stop)
        except OSError:
            os.close(master)
            os.close(slave)
            raise
        self._pty_path = path
        self._spawn(self._serve_pty, link, name="mock-tracker-pty")
        return path

    def stop(self) -> None:
        """Stop serving: close the listening socket and the pty, join the threads."""
        self._stop.set()
        deadline = time.monotonic() + _JOIN_S
        while True:
            with self._lock:
                threads = [t for t in self._threads if t.is_alive()]
                self._threads = threads
            if not threads:
                return
            for thread in threads:
                thread.join(max(0.0, deadline - time.monotonic()))
            if time.monotonic() >= deadline:
                with self._lock:
                    alive = [t.name for t in self._threads if t.is_alive()]
                if alive:
                    log.warning("mock tracker: threads still running after stop: %s", alive)
                return

    def __enter__(self) -> MockTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- threads

    def _spawn(self, target: Callable[..., None], *args: object, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        with self._lock:
            self._threads.append(thread)
        thread.start()

    def _serve_tcp(self, listener: socket.socket) -> None:
        try:
            while not self._stop.is_set():
                try:
                    conn, _ = listener.accept()
                except TimeoutError:
                    continue
                except OSError as exc:
                    log.warning("mock tracker: accept failed (%s)", exc)
                    self._stop.wait(_POLL_S)
                    continue
                with self._lock:
                    self._connections += 1
                    n = self._connections
                self._spawn(self._serve_connection, conn, name=f"mock-tracker-conn-{n}")
        finally:
            listener.close()

    def _serve_connection(self, conn: socket.socket) -> None:
        try:
            conn.setblocking(False)
            with contextlib.suppress(OSError):
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._run_session(_SocketLink(conn, self._stop))
        except _DropLinkError:
            log.info("mock tracker: dropping the connection (fault injection)")
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
        except Exception:
            log.exception("mock tracker: connection failed")
        finally:
            conn.close()

    def _serve_pty(self, link: _PtyLink) -> None:
        try:
            carry = link.wait_open()
            while carry is not None:
                with self._lock:
                    self._connections += 1
                try:
                    self._run_session(link, carry)
                    carry = b""
                except _DropLinkError:
                    log.info("mock tracker: pty stops answering until reopened (fault)")
                    carry = link.mute_until_reopened()
                except Exception:
                    log.exception("mock tracker: pty session failed")
                    carry = link.mute_until_reopened()
                link.flush_stale()
                if carry is not None:
                    carry = link.wait_open(carry)
        finally:
            link.close()

    def _run_session(self, link: _Link, first: bytes = b"") -> None:
        session = _Session(self, link)
        with self._lock:
            self._sessions.add(session)
        try:
            session.run(first)
        except _LinkClosedError:
            pass
        finally:
            with self._lock:
                self._sessions.discard(session)
                if self._owner is session:
                    self._owner = None

    # -- state shared by the sessions

    def _record(self, raw: bytes) -> None:
        with self._lock:
            self._requests.append(raw.decode("ascii", errors="backslashreplace"))

    def _count_event(self) -> None:
        with self._lock:
            self._events_sent += 1

    def _release(self, session: _Session) -> None:
        with self._lock:
            if self._owner is session:
                self._owner = None

    def _status(self) -> str:
        self._poll_beam()
        with self._lock:
            init = self._initialized
            beam = self._beam
            ready = init and beam and self._owner is None
        return f"OK ready={int(ready)} beam={int(beam)} meteo=1 init={int(init)}"

    def _initialise(self) -> str:
        with self._lock:
            if self._owner is not None:
                return _BUSY
            self._initialized = True
            restored = not self._beam
            self._beam = True
            self._restore_at = None
        if restored:
            self._broadcast("EVT BEAM OK")
        return "OK"

    def _set_environment(self, args: list[bytes]) -> str:
        values: dict[bytes, float] = {}
        for arg in args:
            key, eq, text = arg.partition(b"=")
            if not eq or key not in (b"T", b"P", b"RH") or key in values:
                return _BAD
            if not _NUMBER.fullmatch(text):
                return _BAD
            value = float(text)
            if not math.isfinite(value):
                return _BAD
            values[key] = value
        if len(values) != 3:
            return _BAD
        T, P, RH = values[b"T"], values[b"P"], values[b"RH"]
        for v, (lo, hi) in ((T, T_RANGE), (P, P_RANGE), (RH, RH_RANGE)):
            if not lo <= v <= hi:
                return _METEO
        with self._lock:
            self._env = (T, P, RH)
        return "OK"

    def _temperature_reading(self) -> str:
        with self._lock:
            T = self._env[0] + float(self._rng.normal(0.0, 0.05))
        return f"{T + 0.0:.1f}"

    def _break_beam(self) -> None:
        with self._lock:
            self._beam = False
            self._restore_at = time.monotonic() + self.faults.beam_restore_s
            self._breaks_left -= 1

    def _poll_beam(self) -> None:
        with self._lock:
            due = self._restore_at
            if due is None or time.monotonic() < due:
                return
            self._beam = True
            self._restore_at = None
        self._broadcast("EVT BEAM OK")

    def _broadcast(self, event: str) -> None:
        with self._lock:
            sessions = list(self._sessions)
        for session in sessions:
            session.pending_events.append(event)

    def _garbage(self) -> bytes:
        """One line that is not a line of the protocol (no "\\n" in it)."""
        with self._lock:
            rng = self._rng
            if rng.random() < 0.5:
                head = bytes([int(rng.integers(0x80, 0x100))])
                body = rng.integers(0, 256, size=int(rng.integers(0, 40)), dtype=np.uint8)
                return head + bytes(body).replace(b"\n", b"\x00")
            i = int(rng.integers(0, 1000))
            t = f"{float(rng.uniform(0, 100)):.3f}"
            x, y, z = (f"{v:.4f}" for v in rng.uniform(-2000, 2000, 3))
            forms = (
                "PT",
                f"PT {i}",
                f"PT {i} {t} {x} {y}",
                f"PT {i} {t} {x} {y} {z} {x}",
                f"PT {i},{t},{x},{y},{z}",
                f"PT x{i} {t} {x} {y} {z}",
                f"PT {i} {t} {x} {y} 1.2.3",
                f"PT {i} {t} nan nan nan",
                f"PT -{i} {t} {x} {y} {z}",
            )
            return forms[int(rng.integers(0, len(forms)))].encode("ascii")


def serve(options: LineTrackerOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of a configured line-protocol tracker: a MockTracker serving the
    simulated cell's target of this sensor, over TCP on a loopback address."""
    server = MockTracker(cell.target(options.name), time_scale=time_scale)
    host, port = server.start_tcp(TRACKER_HOST, 0)
    twin_options = options.model_copy(
        update={"address": f"socket://{host}:{port}", "timeout_s": max(options.timeout_s, 10.0)}
    )
    return RunningTwin(twin_options, server)
