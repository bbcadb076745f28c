"""Safety in front of every robot driver: no move is sent whose target lies outside the
joint limits or the workspace box, whose path leaves them on the way, or whose speed
exceeds the configured limit; no robot is driven with a model whose joint limits are
missing or not a robot's.

The check uses the nominal model (the calibrated one is not trusted before it exists)
and the target the plan was made for. The robots' moves are joint moves (UR's moveJ,
KUKA's PTP, the Modbus handshake's move command): every joint starts and stops together
and the path is the straight line in joint space from where the robot is to the target.
That line is sampled so finely that no point of the arm out to the target moves more
than :data:`PATH_STEP_MM` between two samples, and at each sample the joints must be
within their limits and the flange origin and the target inside the workspace box.
It is the last gate before a command leaves the PC; the controller's own limits stay
the first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import flange_transforms
from cellcal.calib.robot_model import RobotModel, require_limits
from cellcal.drivers.base import ROBOT_NAME, DeviceDescription, Robot
from cellcal.errors import DeviceError

#: Between two samples of a move's path no point of the arm out to the target moves
#: more than this (mm), so the path between samples leaves the box by less than half
#: (2.5 mm: the gate is there for moves that swing tens of millimetres out; 1 mm steps
#: cost a tracker campaign 0.4 s more for nothing it would catch).
PATH_STEP_MM = 5.0
#: ... with at most this many samples (a 720° turn of every joint of a 2 m arm needs
#: fewer); they are computed this many at a time, so memory stays a few MB.
MAX_PATH_SAMPLES = 200_000
PATH_CHUNK = 4096
#: A point this close outside the box (mm) is on it (rounding of a pose planned on it).
BOX_TOLERANCE_MM = 1e-6


class SafetyError(DeviceError):
    """A move refused before it was sent: the robot's (``device``)."""

    def __init__(self, *args: object, device: str | None = ROBOT_NAME) -> None:
        super().__init__(*args, device=device)

    def at_pose(self, idx: int) -> SafetyError:
        """The same refusal naming the pose of the plan the move was to, as the engine
        names poses (``pose 3: robot: refused …``), so that an operator finds it."""
        return SafetyError(f"pose {idx}: {self}", device=self.device)


@dataclass(frozen=True)
class PathExcursion:
    """The worst point of a move's path outside the workspace box: how far (mm), which
    point (``flange`` or ``target``), where (mm, base frame) and when (fraction of the
    move, 0 at the start)."""

    excess_mm: float
    point: str
    where_mm: Array
    fraction: float


def path_samples(model: RobotModel, q0: Array, q1: Array, target_offset: Array) -> int:
    """How many steps the path from ``q0`` to ``q1`` (rad) is cut into: a turn δ of
    joint i moves a point at distance r from its axis by r·δ, and no point of the arm
    out to the target is farther from any axis than the sum of the link lengths and the
    target offset."""
    reach = sum(math.hypot(j.a, j.d) for j in model.joints)
    reach += float(np.linalg.norm(target_offset))
    turn = float(np.abs(model.reading_matrix @ (np.asarray(q1) - np.asarray(q0))).sum())
    return int(min(MAX_PATH_SAMPLES, max(1, math.ceil(turn * reach / PATH_STEP_MM))))


def _outside(p: Array, lo: Array, hi: Array) -> Array:
    """Distance of each point (N×3) outside the box (0 inside)."""
    d = np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)
    out: Array = np.linalg.norm(d, axis=1)
    return out


def path_excursion(
    model: RobotModel,
    q0: Array,
    q1: Array,
    target_offset: Array,
    box_min_mm: Array,
    box_max_mm: Array,
) -> PathExcursion | None:
    """The worst point of the joint-space straight path from ``q0`` to ``q1`` (rad)
    outside the box, the flange origin's or the target's; None when it stays inside."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    target_offset = np.asarray(target_offset, dtype=np.float64)
    lo = np.asarray(box_min_mm, dtype=np.float64)
    hi = np.asarray(box_max_mm, dtype=np.float64)
    n = path_samples(model, q0, q1, target_offset)
    s_all = np.linspace(0.0, 1.0, n + 1)
    worst: PathExcursion | None = None
    for start in range(0, n + 1, PATH_CHUNK):
        s = s_all[start : start + PATH_CHUNK]
        T = flange_transforms(model, q0 + s[:, None] * (q1 - q0))
        flange = T[:, :3, 3]
        target = flange + T[:, :3, :3] @ target_offset
        for name, p in (("flange", flange), ("target", target)):
            out = _outside(p, lo, hi)
            k = int(np.argmax(out))
            if out[k] > BOX_TOLERANCE_MM and (worst is None or out[k] > worst.excess_mm):
                worst = PathExcursion(float(out[k]), name, p[k].copy(), float(s[k]))
    return worst


def _deg(q: Array) -> list[float]:
    return [round(float(v), 3) + 0.0 for v in np.degrees(q)]


class GuardedRobot:
    """A :class:`~cellcal.drivers.base.Robot` whose moves are checked first. A model
    without finite, plausible joint limits is refused when the gate is built."""

    def __init__(
        self,
        robot: Robot,
        model: RobotModel,
        target_offset: Array,
        box_min_mm: Array,
        box_max_mm: Array,
        max_speed: float,
    ) -> None:
        require_limits(model, f"robot model {model.name!r}")
        self.robot = robot
        self.name = robot.name
        self.model = model
        self.target_offset = np.asarray(target_offset, dtype=np.float64)
        self.box_min = np.asarray(box_min_mm, dtype=np.float64)
        self.box_max = np.asarray(box_max_mm, dtype=np.float64)
        self.max_speed = max_speed
        self.refused = 0

    def check(self, q: Array, speed: float) -> None:
        """Raise :class:`SafetyError` if a move to ``q`` may not be sent (its end)."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.model.dof,) or not np.isfinite(q).all():
            raise SafetyError(f"{self.name}: refused a move to a malformed joint target {q}")
        if not (0 < speed <= self.max_speed) or not math.isfinite(speed):
            raise SafetyError(
                f"{self.name}: refused a move at speed {speed:g}; the limit is {self.max_speed:g}"
            )
        self._check_limits(q, f"{self.name}: refused a move")
        T = flange_transforms(self.model, q[None])[0]
        p = T[:3, 3] + T[:3, :3] @ self.target_offset
        if (p < self.box_min).any() or (p > self.box_max).any():
            raise SafetyError(
                f"{self.name}: refused a move: the target would be at "
                f"{np.round(p, 1).tolist()} mm, outside the workspace box"
            )

    def _check_limits(self, q: Array, what: str) -> None:
        lo, hi = self.model.limits
        j = self.model.joint_outside_limits(q)
        if j is not None:
            raise SafetyError(
                f"{what}: joint {j + 1} to {math.degrees(q[j]):.3f}° is "
                f"outside [{math.degrees(lo[j]):.1f}°, {math.degrees(hi[j]):.1f}°]"
            )

    def check_path(self, q0: Array, q1: Array) -> None:
        """Raise :class:`SafetyError` if the joint move from ``q0`` (where the robot is)
        to ``q1`` leaves the joint limits or the workspace box on the way."""
        q0 = np.asarray(q0, dtype=np.float64)
        q1 = np.asarray(q1, dtype=np.float64)
        if q0.shape != (self.model.dof,) or not np.isfinite(q0).all():
            raise SafetyError(f"{self.name}: refused a move: the robot reports joints {q0}")
        self._check_limits(q0, f"{self.name}: refused a move to {_deg(q1)}°: the robot is at")
        far = path_excursion(self.model, q0, q1, self.target_offset, self.box_min, self.box_max)
        if far is None:
            return
        where = np.round(far.where_mm, 1).tolist()
        if far.fraction == 0.0:
            raise SafetyError(
                f"{self.name}: refused a move to {_deg(q1)}°: the robot is at {_deg(q0)}°, "
                f"its {far.point} {far.excess_mm:.1f} mm outside the workspace box (at "
                f"{where} mm); jog it inside first"
            )
        if far.fraction == 1.0:
            raise SafetyError(
                f"{self.name}: refused a move to {_deg(q1)}°: its {far.point} would be "
                f"{far.excess_mm:.1f} mm outside the workspace box (at {where} mm)"
            )
        raise SafetyError(
            f"{self.name}: refused the move from {_deg(q0)}° to {_deg(q1)}°: on the way "
            f"({100 * far.fraction:.0f} % of the joint move) its {far.point} leaves the "
            f"workspace box by {far.excess_mm:.1f} mm (at {where} mm)"
        )

    def connect(self) -> None:
        self.robot.connect()

    def move_joints(self, q: Array, speed: float) -> None:
        try:
            self.check(q, speed)
            self.check_path(self.robot.actual_joints(), q)
        except SafetyError:
            self.refused += 1
            raise
        self.robot.move_joints(q, speed)

    def actual_joints(self) -> Array:
        return self.robot.actual_joints()

    def joint_temperatures(self) -> Array | None:
        """The joints' temperatures (°C) where the robot's driver reads them, else None."""
        read = getattr(self.robot, "joint_temperatures", None)
        return None if read is None else np.asarray(read(), dtype=np.float64)

    def describe(self) -> DeviceDescription:
        return self.robot.describe()

    def stop(self) -> None:
        self.robot.stop()

    def close(self) -> None:
        self.robot.close()
