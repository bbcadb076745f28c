"""What the engine needs of a device: small Protocols, and the values they return.

Drivers convert to and from device units at their edge; through these Protocols joint
positions are radians and lengths millimetres. Every call may raise a
:class:`~cellcal.errors.DeviceError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.clock import Clock, WallClock


@dataclass(frozen=True)
class DeviceContext:
    """What a driver may need beyond its options when it is built: the clock it takes
    time on, and in mock mode the simulated cell (which only the in-process simulated
    devices read; a real driver never looks at it)."""

    clock: Clock = field(default_factory=WallClock)
    cell: Any = None


def label(name: str, address: str) -> str:
    """How every device is named in messages: "name at address"."""
    return f"{name} at {address}" if address else name


def host_port(address: str, default_port: int) -> tuple[str, int]:
    """``host`` or ``host:port`` (an IPv6 host in brackets) → (host, port)."""
    host, sep, port = address.rpartition(":")
    if sep and port.isdigit() and not host.endswith(":"):
        return host.strip("[]"), int(port)
    return address.strip("[]"), default_port


@dataclass(frozen=True)
class Series:
    """One sensor's samples at one pose: host and device timestamps (s) and positions
    (N×3, mm, in the sensor's frame); ``retries`` counts re-measurements after faults.

    A sensor that knows each sample's uncertainty (the photogrammetry rig) adds ``cov``
    (N×3×3, mm²), the target's orientation in its frame (``orientation``, N×4 unit
    quaternions w, x, y, z) and the covariance of the mean (``mean_cov``, 3×3, mm², which
    may hold a part that does not average over samples). ``note`` says what went wrong on
    the way (sets or points that failed and were taken again, frames lost) and, for a
    series with fewer samples than asked (its driver's re-takes ran out: at most twice
    as many), why."""

    sensor: str
    host_time: Array
    device_time: Array
    xyz: Array
    retries: int = 0
    cov: Array | None = None
    orientation: Array | None = None
    mean_cov: Array | None = None
    note: str = ""

    def __post_init__(self) -> None:
        n = len(self.xyz)
        if self.xyz.shape != (n, 3) or len(self.host_time) != n or len(self.device_time) != n:
            raise ValueError("series: timestamps and positions must have the same length")
        if self.cov is not None and self.cov.shape != (n, 3, 3):
            raise ValueError("series: one 3×3 covariance per sample")
        if self.orientation is not None and self.orientation.shape != (n, 4):
            raise ValueError("series: one quaternion (w, x, y, z) per sample")
        if self.mean_cov is not None and self.mean_cov.shape != (3, 3):
            raise ValueError("series: the mean's covariance is 3×3")

    @property
    def n(self) -> int:
        return len(self.xyz)

    @property
    def mean(self) -> Array:
        out: Array = self.xyz.mean(axis=0)
        return out

    @property
    def std(self) -> Array:
        """Sample standard deviation per axis (mm); zeros for a single sample."""
        if self.n < 2:
            return np.zeros(3)
        out: Array = self.xyz.std(axis=0, ddof=1)
        return out

    @property
    def mean_covariance(self) -> Array | None:
        """The covariance of the mean (mm²) when the sensor gave one: ``mean_cov``, else
        the samples' covariances averaged over n; None for a sensor without them."""
        if self.mean_cov is not None:
            return self.mean_cov
        if self.cov is None or self.n == 0:
            return None
        out: Array = self.cov.mean(axis=0) / self.n
        return out


class Robot(Protocol):
    """A robot controller that moves to joint positions and reports where it is."""

    name: str

    def connect(self) -> None: ...

    def move_joints(self, q: Array, speed: float) -> None:
        """Move to ``q`` (rad) at ``speed`` (fraction of maximum); return once the robot
        reports it is in position."""
        ...

    def actual_joints(self) -> Array:
        """The joint positions the controller reports (rad)."""
        ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


class PositionSensor(Protocol):
    """A sensor that measures the position of its target (laser tracker,
    photogrammetry rig)."""

    name: str

    def connect(self) -> None: ...

    def measure(self, n: int, rate_hz: float) -> Series:
        """``n`` samples at ``rate_hz``; blocks for about n / rate_hz seconds. What fails
        is taken again, at most ``2 n`` attempts in all; a series still short comes back
        with what it has and a note saying why."""
        ...

    def close(self) -> None: ...
