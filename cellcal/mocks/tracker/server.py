"""A protocol-level mock laser tracker: tracker line protocol versions 1 and 2
(``docs/tracker.md``) over TCP on a loopback address or over a
pseudo-terminal, so that the real driver runs unchanged against it in CI and in
``cellcal mock tracker``.

It is made of three modules: ``link_server`` (the TCP and pty link servers, a thread a
connection), ``tracker_session`` (the protocol codec and one connection's session) and
this one, the tracker state and ``serve``.

The tracker state (initialised, beam, environment, reflector, its own clock) belongs to
the tracker and outlives a connection; what concerns one link (line counters for the
fault cadences, a running series) belongs to the connection's ``TrackerSession``. One
series runs at a time, whichever connection started it.

* Version 2's covariance is the simulated noise's where the target is
  (``emscon_server.noise_covariance``, as the emScon twin's) for the simulated cell's
  target, else ``covariance`` (by default 10 µm in every direction); its air is the
  environment the tracker holds (``ENV``).
* ``STAT?``: ``ready`` = initialised and beam and no series running; ``meteo`` = 1 (the
  environment can only hold values within range).
* After a beam break, ``EVT BEAM OK`` goes to every connection when the beam is back
  (``beam_restore_s`` later, or at ``INIT``).
* The faults apply to every connection; ``drop_after_lines`` counts the lines of each
  one: after that many lines a TCP connection is shut down (FIN), a pty stops answering
  until the client closes and reopens it.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from cellcal.mocks.link_server import JOIN_S, Link, PtyLinkServer, TcpLinkServer
from cellcal.mocks.tracker.session import (
    BEAM_BROKEN,
    BUSY,
    DEFAULT_RATE_HZ,
    MAX_LINE,
    MAX_POINTS,
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    NOT_INITIALIZED,
    P_RANGE,
    REFLECTORS,
    RH_RANGE,
    T_RANGE,
    TrackerSession,
)
from cellcal.mocks.twins import TRACKER_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.calib.geometry import Array
    from cellcal.drivers.tracker import LineTrackerOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

__all__ = [
    "DEFAULT_RATE_HZ",
    "FIRMWARE",
    "MAKER",
    "MAX_LINE",
    "MAX_POINTS",
    "MAX_RATE_HZ",
    "MIN_RATE_HZ",
    "MODEL",
    "P_RANGE",
    "REFLECTORS",
    "RH_RANGE",
    "T_RANGE",
    "VERSIONS",
    "TargetSource",
    "TrackerFaults",
    "TrackerTwin",
    "serve",
]

log = logging.getLogger("cellcal.mocks.tracker")

MAKER = "cellcal"
MODEL = "mock-tracker"
FIRMWARE = "1.0"
#: The versions of the line protocol the twin speaks.
VERSIONS = (1, 2)
#: Version 2's covariance (mm²) of a target that is not the simulated cell's: 10 µm.
COVARIANCE = np.eye(3) * 0.010**2

_SERIAL = re.compile(r"[\x21-\x7e]+")


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
    beam_break_every: int = 0  # every N-th series loses the beam half-way (0: never)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("beam_break_after", "drop_after_lines"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ValueError(f"TrackerFaults.{name} must be >= 0 or None, got {value}")
        for name in ("beam_breaks", "garbage_every", "event_every", "beam_break_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"TrackerFaults.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("beam_restore_s", "reply_delay_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"TrackerFaults.{name} must be finite and >= 0, got {value}")


class TrackerTwin:
    """A simulated laser tracker serving the tracker line protocol, versions 1 and 2
    (``versions=(1,)``: a tracker of version 1 alone, which knows no ``PROTO``).

    ``time_scale`` 0 streams points as fast as possible; > 0 waits
    (1/rate)·time_scale wall seconds between points. ``requests`` keeps the last
    :attr:`REQUEST_LOG` request lines (a long client's do not pile up). ``covariance``:
    version 2's covariance of each point (3×3, mm²), by default the simulated noise's for
    the simulated cell's target (:func:`noise_of`).
    """

    REQUEST_LOG = 10000

    def __init__(
        self,
        source: TargetSource,
        *,
        faults: TrackerFaults = TrackerFaults(),
        serial: str = "SIM-0001",
        time_scale: float = 0.0,
        clock_start: float = 12.0,
        versions: tuple[int, ...] = VERSIONS,
        covariance: Callable[[], Array] | None = None,
    ) -> None:
        if not _SERIAL.fullmatch(serial) or "," in serial:
            raise ValueError(f"serial {serial!r}: printable ASCII without spaces or commas")
        if not (math.isfinite(time_scale) and time_scale >= 0):
            raise ValueError(f"time_scale must be finite and >= 0, got {time_scale}")
        if not math.isfinite(clock_start):
            raise ValueError(f"clock_start must be finite, got {clock_start}")
        if versions not in ((1,), VERSIONS):
            raise ValueError(f"versions must be (1,) or {VERSIONS}, got {versions}")
        self.source = source
        self.versions = versions
        self._covariance = covariance or noise_of(source)
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
        self._series = 0
        self._env = (20.0, 1013.25, 45.0)
        self._smr = REFLECTORS[0]
        self._clock = float(clock_start)
        self._owner: TrackerSession | None = None
        self._sessions: set[TrackerSession] = set()
        self._requests: deque[str] = deque(maxlen=self.REQUEST_LOG)
        self._events_sent = 0
        self._tcp = TcpLinkServer(self._serve, name="tracker-twin", stop=self._stop, log=log)
        self._pty = PtyLinkServer(self._serve, name="tracker-twin", stop=self._stop, log=log)

    # -- public

    @property
    def events_sent(self) -> int:
        with self._lock:
            return self._events_sent

    @property
    def requests(self) -> list[str]:
        """The last :attr:`REQUEST_LOG` request lines received (empty lines not), oldest
        first; a copy."""
        with self._lock:
            return list(self._requests)

    @property
    def connections(self) -> int:
        """TCP connections accepted plus pty opens seen."""
        return self._tcp.connections + self._pty.connections

    @property
    def threads(self) -> list[threading.Thread]:
        """The serving threads still running."""
        return self._tcp.threads + self._pty.threads

    def start_tcp(self, host: str = "127.0.0.5", port: int = 0) -> tuple[str, int]:
        """Listen on (host, port) (port 0: any free one) and serve in the background;
        returns the bound address once listening."""
        return self._tcp.start(host, port)

    def start_pty(self) -> str:
        """Open a pseudo-terminal, serve its master side in the background and return the
        slave's path (open it with pyserial, e.g. ``serial.Serial(path)``)."""
        return self._pty.start()

    def stop(self) -> None:
        """Stop serving: close the listening socket and the pty, join the threads."""
        self._stop.set()
        deadline = time.monotonic() + JOIN_S
        for server in (self._tcp, self._pty):
            server.stop(max(0.0, deadline - time.monotonic()))

    def __enter__(self) -> TrackerTwin:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- one connection (a thread of the link server)

    def _serve(self, link: Link) -> None:
        session = TrackerSession(self, link)
        with self._lock:
            self._sessions.add(session)
        try:
            session.run()
        finally:
            with self._lock:
                self._sessions.discard(session)
                if self._owner is session:
                    self._owner = None

    # -- state shared by the sessions (tracker_session)

    def _record(self, raw: bytes) -> None:
        with self._lock:
            self._requests.append(raw.decode("ascii", errors="backslashreplace"))

    def _count_event(self) -> None:
        with self._lock:
            self._events_sent += 1

    def _identity(self) -> str:
        return f"{MAKER},{MODEL},{self.serial},{FIRMWARE}"

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
                return BUSY
            self._initialized = True
            restored = not self._beam
            self._beam = True
            self._restore_at = None
        if restored:
            self._broadcast("EVT BEAM OK")
        return "OK"

    def _environment(self) -> tuple[float, float, float]:
        with self._lock:
            return self._env

    def _set_environment(self, env: tuple[float, float, float]) -> None:
        with self._lock:
            self._env = env

    def _reflector(self) -> str:
        with self._lock:
            return self._smr

    def _set_reflector(self, name: str) -> None:
        with self._lock:
            self._smr = name

    def _temperature_reading(self) -> str:
        with self._lock:
            T = self._env[0] + float(self._rng.normal(0.0, 0.05))
        return f"{T + 0.0:.1f}"

    def _busy(self) -> bool:
        """Whether a series runs."""
        with self._lock:
            return self._owner is not None

    def _claim(self, session: TrackerSession) -> str | None:
        """Make ``session`` the one running a series; None, or the reason it cannot."""
        with self._lock:
            if self._owner is not None:
                return BUSY
            if not self._initialized:
                return NOT_INITIALIZED
            if not self._beam:
                return BEAM_BROKEN
            self._owner = session
        return None

    def _release(self, session: TrackerSession) -> None:
        with self._lock:
            if self._owner is session:
                self._owner = None

    def _series_start(self, n: int) -> tuple[float, int | None]:
        """The clock at the start of a series of ``n`` points, and after how many points
        the beam breaks in it (None: it does not)."""
        with self._lock:
            k = self.faults.beam_break_after
            break_at = k if k is not None and self._breaks_left > 0 and k < n else None
            every = self.faults.beam_break_every
            self._series += 1
            if every and self._series % every == 0 and n > 1:
                self._breaks_left += 1  # _break_beam counts it
                break_at = n // 2
            return self._clock, break_at

    def _set_clock(self, t: float) -> None:
        with self._lock:
            self._clock = t

    def _break_beam(self) -> None:
        with self._lock:
            self._beam = False
            self._restore_at = time.monotonic() + self.faults.beam_restore_s
            self._breaks_left -= 1

    def _beam_restore_due(self) -> float | None:
        """When a broken beam comes back (time.monotonic), None if it is not broken."""
        return self._restore_at

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


def noise_of(source: TargetSource) -> Callable[[], Array]:
    """Version 2's covariance of ``source``'s points: for the simulated cell's target the
    covariance of its noise where the target is now, else :data:`COVARIANCE`."""
    from cellcal.mocks.simulated_cell import CellTarget
    from cellcal.mocks.tracker.emscon_server import noise_covariance

    if isinstance(source, CellTarget):
        return lambda: noise_covariance(source.cell, source.sensor)
    return lambda: COVARIANCE


def serve(options: LineTrackerOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of a configured line-protocol tracker: a TrackerTwin serving the
    simulated cell's target of this sensor, over TCP on a loopback address."""
    f = cell.faults
    faults = TrackerFaults(
        beam_break_every=f.tracker_beam_break_every,
        beam_restore_s=f.tracker_beam_restore_s,
        drop_after_lines=f.tracker_drop_after_lines or None,
    )
    server = TrackerTwin(cell.target(options.name), faults=faults, time_scale=time_scale)
    host, port = server.start_tcp(TRACKER_HOST, 0)
    twin_options = options.model_copy(
        update={"address": f"socket://{host}:{port}", "timeout_s": max(options.timeout_s, 10.0)}
    )
    return RunningTwin(twin_options, server)
