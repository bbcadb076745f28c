"""Clocks: the engine and the simulated devices take one, so that a 7 s dwell costs 7 s
on a real cell and no wall time in CI, while the plan still says 7 s.

``SimulatedClock`` keeps virtual time. ``sleep(dt)`` from any thread means "until
now + dt": virtual time moves to the latest deadline reached, so two instruments that
each measure for 2 s side by side cost 2 s, not 4. With ``time_scale`` > 0 each sleep
also waits ``dt × time_scale`` wall seconds (a demo at 1/100 speed).
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Monotonic seconds."""
        ...

    def sleep(self, seconds: float) -> None: ...


class WallClock:
    """Real time."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SimulatedClock:
    """Virtual time starting at ``start``; thread-safe."""

    def __init__(self, time_scale: float = 0.0, start: float = 0.0) -> None:
        if time_scale < 0:
            raise ValueError("time_scale must be >= 0")
        self.time_scale = time_scale
        self._now = start
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._now

    def sleep(self, seconds: float) -> None:
        if seconds <= 0:
            return
        with self._lock:
            deadline = self._now + seconds
        if self.time_scale > 0:
            time.sleep(seconds * self.time_scale)
        with self._lock:
            self._now = max(self._now, deadline)
