"""Safety in front of every robot driver: no move is sent whose target lies outside the
joint limits or the workspace box, or whose speed exceeds the configured limit.

The check uses the nominal model (the calibrated one is not trusted before it exists)
and the target the plan was made for. It is the last gate before a command leaves the
PC; the controller's own limits stay the first.
"""

from __future__ import annotations

import math

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.drivers.base import Robot
from cellcal.errors import DeviceError


class SafetyError(DeviceError):
    """A move refused before it was sent."""


class GuardedRobot:
    """A :class:`~cellcal.drivers.base.Robot` whose moves are checked first."""

    def __init__(
        self,
        robot: Robot,
        model: RobotModel,
        target_offset: Array,
        box_min_mm: Array,
        box_max_mm: Array,
        max_speed: float,
    ) -> None:
        self.robot = robot
        self.name = robot.name
        self.model = model
        self.target_offset = np.asarray(target_offset, dtype=np.float64)
        self.box_min = np.asarray(box_min_mm, dtype=np.float64)
        self.box_max = np.asarray(box_max_mm, dtype=np.float64)
        self.max_speed = max_speed
        self.refused = 0

    def check(self, q: Array, speed: float) -> None:
        """Raise :class:`SafetyError` if the move may not be sent."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.model.dof,) or not np.isfinite(q).all():
            raise SafetyError(f"{self.name}: refused a move to a malformed joint target {q}")
        if not (0 < speed <= self.max_speed) or not math.isfinite(speed):
            raise SafetyError(
                f"{self.name}: refused a move at speed {speed:g}; the limit is {self.max_speed:g}"
            )
        lo, hi = self.model.limits
        bad = np.flatnonzero((q < lo - 1e-9) | (q > hi + 1e-9))
        if len(bad):
            j = int(bad[0])
            raise SafetyError(
                f"{self.name}: refused a move: joint {j + 1} to {math.degrees(q[j]):.3f}° is "
                f"outside [{math.degrees(lo[j]):.1f}°, {math.degrees(hi[j]):.1f}°]"
            )
        p = target_kinematics(self.model, q[None], self.target_offset, jacobian=False).p[0]
        if (p < self.box_min).any() or (p > self.box_max).any():
            raise SafetyError(
                f"{self.name}: refused a move: the target would be at "
                f"{np.round(p, 1).tolist()} mm, outside the workspace box"
            )

    def connect(self) -> None:
        self.robot.connect()

    def move_joints(self, q: Array, speed: float) -> None:
        try:
            self.check(q, speed)
        except SafetyError:
            self.refused += 1
            raise
        self.robot.move_joints(q, speed)

    def actual_joints(self) -> Array:
        return self.robot.actual_joints()

    def stop(self) -> None:
        self.robot.stop()

    def close(self) -> None:
        self.robot.close()
