"""Clocks: the engine and the simulated devices take one, so that a 7 s dwell costs 7 s
on a real cell and no wall time in CI, while the plan still says 7 s.

``SimulatedClock`` keeps virtual time: ``sleep(dt)`` moves it forward by dt. Work that
runs side by side (the sensors of one pose, each in its own thread) runs inside
``branch(start)``: each branch keeps its own time from the common start, and the clock
moves to the latest time any branch reached — two sensors that each measure for
2 s side by side cost 2 s, not 4. With ``time_scale`` > 0 every sleep also waits
``dt × time_scale`` wall seconds (0.01: a hundred times faster than the real cell).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Monotonic seconds."""
        ...

    def sleep(self, seconds: float) -> None: ...

    def wait(self, event: threading.Event, seconds: float) -> bool:
        """Sleep up to ``seconds``, less if ``event`` is set first; whether it was set
        (a dwell that a stop request cuts short)."""
        ...

    def branch(self, start: float) -> AbstractContextManager[None]:
        """Context for work running concurrently with other branches from ``start``."""
        ...


class WallClock:
    """Real time; branches need nothing special."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def wait(self, event: threading.Event, seconds: float) -> bool:
        return event.wait(seconds) if seconds > 0 else event.is_set()

    @contextmanager
    def branch(self, start: float) -> Iterator[None]:
        yield


class SimulatedClock:
    """Virtual time starting at ``start``; thread-safe."""

    def __init__(self, time_scale: float = 0.0, start: float = 0.0) -> None:
        if time_scale < 0:
            raise ValueError("time_scale must be >= 0")
        self.time_scale = time_scale
        self._now = start
        self._lock = threading.Lock()
        self._local = threading.local()

    def now(self) -> float:
        local = getattr(self._local, "t", None)
        if local is not None:
            return float(local)
        with self._lock:
            return self._now

    def sleep(self, seconds: float) -> None:
        if seconds <= 0:
            return
        if self.time_scale > 0:
            time.sleep(seconds * self.time_scale)
        self._advance(seconds)

    def wait(self, event: threading.Event, seconds: float) -> bool:
        """As ``sleep``, cut short when ``event`` is set: with ``time_scale`` 0 only a
        stop already requested cuts it; otherwise virtual time advances by the wall
        time waited (÷ time_scale)."""
        if event.is_set():
            return True
        if seconds <= 0:
            return False
        if self.time_scale <= 0:
            self.sleep(seconds)
            return event.is_set()
        t0 = time.monotonic()
        hit = event.wait(seconds * self.time_scale)
        waited = min(seconds, (time.monotonic() - t0) / self.time_scale) if hit else seconds
        self._advance(waited)
        return hit

    def _advance(self, seconds: float) -> None:
        local = getattr(self._local, "t", None)
        with self._lock:
            deadline = (self._now if local is None else local) + seconds
            self._now = max(self._now, deadline)
        if local is not None:
            self._local.t = deadline

    @contextmanager
    def branch(self, start: float) -> Iterator[None]:
        self._local.t = start
        try:
            yield
        finally:
            self._local.t = None
