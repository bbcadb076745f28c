"""Fusing what several sensors measured of one pose, after registration.

Each sensor follows its own target on the flange (the tracker's SMR, the rig's marker
fixture), measured in its own frame. Once each sensor is registered to the robot base
(``T_sensor_base`` and its target offset, fitted with the same robot model), a sensor's
mean position is taken to the base frame and carried along the flange from its target
to the reference target, ``p + R_base_flange(q) · (offset_reference − offset_sensor)``;
the estimates of the reference point are then combined by their covariances (the
information-weighted mean). Their agreement is the χ² of the estimates about the fused
value (3(k−1) degrees of freedom for k sensors): about 1 per degree of freedom when each
sensor's covariance tells the truth and the registration holds.

The covariance of the carried estimate is the sensor's, rotated: the flange's orientation
error over the lever between the targets (0.1 mrad × 100 mm = 0.01 mm) is not in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.errors import InputError


@dataclass(frozen=True)
class Estimate:
    """One sensor's estimate of a point in the robot base frame (mm, mm²)."""

    sensor: str
    xyz: Array
    cov: Array


@dataclass(frozen=True)
class Fused:
    """The combined estimate of a point (base frame, mm; covariance mm²), the sensors it
    came from, and their χ² about it (None for one sensor)."""

    xyz: Array
    cov: Array
    sensors: tuple[str, ...]
    chi2: float | None

    @property
    def dof(self) -> int:
        return 3 * (len(self.sensors) - 1)


def in_base(sensor: str, xyz: Array, cov: Array, T_sensor_base: Array) -> Estimate:
    """A sensor's mean position and its covariance, taken to the robot base frame."""
    R, t = T_sensor_base[:3, :3], T_sensor_base[:3, 3]
    return Estimate(sensor, R.T @ (np.asarray(xyz) - t), R.T @ np.asarray(cov) @ R)


def carried(e: Estimate, R_base_flange: Array, offset_from: Array, offset_to: Array) -> Estimate:
    """An estimate of one target carried along the flange to another target's point."""
    shift = R_base_flange @ (np.asarray(offset_to) - np.asarray(offset_from))
    return Estimate(e.sensor, e.xyz + shift, e.cov)


def fuse(estimates: list[Estimate]) -> Fused:
    """The information-weighted mean of estimates of one point."""
    if not estimates:
        raise InputError("fuse: no estimate to fuse")
    info = [np.linalg.inv(e.cov) for e in estimates]
    cov = np.linalg.inv(np.sum(info, axis=0))
    cov = 0.5 * (cov + cov.T)
    xyz = cov @ np.sum([W @ e.xyz for W, e in zip(info, estimates, strict=True)], axis=0)
    chi2 = None
    if len(estimates) > 1:
        chi2 = float(
            sum((e.xyz - xyz) @ W @ (e.xyz - xyz) for W, e in zip(info, estimates, strict=True))
        )
    return Fused(xyz, cov, tuple(e.sensor for e in estimates), chi2)
