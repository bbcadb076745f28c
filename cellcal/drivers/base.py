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
    (N×3, mm, in the sensor's frame); ``retries`` counts re-measurements after faults."""

    sensor: str
    host_time: Array
    device_time: Array
    xyz: Array
    retries: int = 0

    def __post_init__(self) -> None:
        n = len(self.xyz)
        if self.xyz.shape != (n, 3) or len(self.host_time) != n or len(self.device_time) != n:
            raise ValueError("series: timestamps and positions must have the same length")

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
        """``n`` samples at ``rate_hz``; blocks for about n / rate_hz seconds."""
        ...

    def close(self) -> None: ...
