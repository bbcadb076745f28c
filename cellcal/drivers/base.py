"""What the engine needs of a device: small Protocols, and the values they return.

Drivers convert to and from device units at their edge; through these Protocols joint
positions are radians and lengths millimetres. Every call may raise a
:class:`~cellcal.errors.DeviceError`, whose ``device`` is the device's name in the
configuration (:data:`ROBOT_NAME` for the robot, a sensor's own name). ``describe()``
says what the device is (:class:`DeviceDescription`), for the campaign's record.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Concatenate, ParamSpec, Protocol, TypeVar

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.clock import Clock, WallClock
from cellcal.errors import device_errors

#: The robot's name in the configuration (its section, ``[robot]``: a cell has one): what
#: its DeviceErrors and its description name, whatever its driver calls it in messages.
ROBOT_NAME = "robot"


@dataclass(frozen=True)
class DeviceDescription:
    """What a device is, for the campaign's record: its name in the configuration
    (``device``), its family (the tag of ``cellcal/families.py``: ``ur``, ``modbus``,
    ``laser-tracker/line-protocol``, …), where it is (``address``; None for an
    in-process simulation) and what its protocol tells of it — ``maker``, ``model``,
    ``firmware``, ``serial`` — each None where the protocol cannot say. ``parts``: the
    devices it is made of, described alike (a photogrammetry rig's cameras, each
    ``device`` the camera's name in the rig)."""

    device: str
    family: str
    address: str | None = None
    maker: str | None = None
    model: str | None = None
    firmware: str | None = None
    serial: str | None = None
    parts: tuple[DeviceDescription, ...] = ()


@dataclass(frozen=True)
class DeviceContext:
    """What a driver may need beyond its options when it is built: the clock it takes
    time on, in mock mode the simulated cell (which only the in-process simulated
    devices read; a real driver never looks at it), and ``report(device, message)``,
    where a device that takes long to get ready (a tracker warming up, initialising)
    says what it is doing — the service shows it in its status."""

    clock: Clock = field(default_factory=WallClock)
    cell: Any = None
    report: Callable[[str, str], None] | None = None


class _Named(Protocol):
    name: str


_P = ParamSpec("_P")
_R = TypeVar("_R")
_D = TypeVar("_D", bound=_Named)


def naming_errors(method: Callable[Concatenate[_D, _P], _R]) -> Callable[Concatenate[_D, _P], _R]:
    """A driver's method whose DeviceErrors name the device (``device``: its ``name``)
    when they do not yet: those of the layers below too (a transport, a camera backend),
    which do not know it. For a driver whose ``name`` is its name in the configuration:
    a sensor's."""

    @functools.wraps(method)
    def named(self: _D, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with device_errors(self.name):
            return method(self, *args, **kwargs)

    return named


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
    may hold a part that does not average over samples). A sensor that reports the air it
    compensated each sample with (a laser tracker's meteo) adds ``meteo`` (N×3: °C, hPa,
    %RH). ``note`` says what went wrong on
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
    meteo: Array | None = None

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
        if self.meteo is not None and self.meteo.shape != (n, 3):
            raise ValueError("series: one temperature, pressure and humidity per sample")

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

    def describe(self) -> DeviceDescription:
        """What the controller is (connected: what it says of itself)."""
        ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


class PositionSensor(Protocol):
    """A sensor that measures the position of its target (laser tracker,
    photogrammetry rig)."""

    #: its name in the configuration: what its DeviceErrors and its description name
    name: str

    def connect(self) -> None: ...

    def measure(self, n: int, rate_hz: float) -> Series:
        """``n`` samples at ``rate_hz``; blocks for about n / rate_hz seconds. What fails
        is taken again, at most ``2 n`` attempts in all; a series still short comes back
        with what it has and a note saying why."""
        ...

    def describe(self) -> DeviceDescription:
        """What the sensor is (connected: what it says of itself)."""
        ...

    def close(self) -> None: ...
