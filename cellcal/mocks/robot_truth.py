"""Ground truth of a simulated robot: a nominal model with seeded kinematic errors, an
sensor placed somewhere in the cell, a target offset on the flange, and noisy
measurements of the target. Every function takes a numpy Generator: same seed, same
robot, same measurements."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from cellcal.calib.error_terms import HARMONICS, RATIO, Conditions, Term
from cellcal.calib.geometry import Array, so3_exp
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import InputError

if TYPE_CHECKING:
    from cellcal.simulation_config import SimulatedChange, SimulatedTerms


@dataclass(frozen=True)
class TrueCell:
    """The simulated truth: real geometry, target offset (mm) and T_sensor_base."""

    model: RobotModel
    target_offset: Array
    T_sensor_base: Array

    def positions(self, q: Array, conditions: Conditions | None = None) -> Array:
        """Noise-free target positions in the sensor frame (mm) for q (rad), at the
        ``conditions`` (time, temperature, payload) the model's error terms read."""
        p = target_kinematics(
            self.model, q, self.target_offset, jacobian=False, conditions=conditions
        ).p
        out: Array = p @ self.T_sensor_base[:3, :3].T + self.T_sensor_base[:3, 3]
        return out


def perturbed_model(
    nominal: RobotModel,
    rng: np.random.Generator,
    *,
    length_mm: float = 0.3,
    angle_deg: float = 0.03,
) -> RobotModel:
    """Nominal geometry plus uniform errors: lengths (a, d) ±length_mm, angles (θ, α)
    ±angle_deg, and a tilt β of the same size on rows with parallel axes."""
    ang = math.radians(angle_deg)
    joints = []
    for j, par in zip(nominal.joints, nominal.parallel, strict=True):
        joints.append(
            replace(
                j,
                a=j.a + rng.uniform(-length_mm, length_mm),
                d=j.d + rng.uniform(-length_mm, length_mm),
                theta=j.theta + rng.uniform(-ang, ang),
                alpha=j.alpha + rng.uniform(-ang, ang),
                beta=j.beta + (rng.uniform(-ang, ang) if par else 0.0),
            )
        )
    return nominal.with_joints(tuple(joints))


def changed_model(model: RobotModel, change: SimulatedChange) -> RobotModel:
    """``model`` after ``change`` (``[simulation.change]``): θ offsets (deg) added to the
    joints, link lengths (``a2``, ``d4``: mm) added; one line naming a key that does not
    fit the robot."""
    n = model.dof
    offsets = list(change.joint_offset_deg)
    if offsets and len(offsets) != n:
        raise InputError(
            f"simulation.change.joint_offset_deg: {len(offsets)} values for a robot of {n} "
            "joints (one a joint, or none)"
        )
    joints = list(model.joints)
    for i, off in enumerate(offsets):
        joints[i] = replace(joints[i], theta=joints[i].theta + math.radians(off))
    for name, mm in change.link_mm.items():
        i = int(name[1:]) - 1
        if i >= n:
            raise InputError(f"simulation.change.link_mm: {name}: the robot has {n} joints")
        field = name[0]
        joints[i] = replace(joints[i], **{field: getattr(joints[i], field) + mm})
    return model.with_joints(tuple(joints))


def grown_model(model: RobotModel, reach_mm: float) -> RobotModel:
    """``model`` with its reach (the sum of its link lengths |a| + |d|) grown by
    ``reach_mm``, each length in proportion to its own (thermal growth)."""
    reach = sum(abs(j.a) + abs(j.d) for j in model.joints)
    if reach_mm == 0 or reach == 0:
        return model
    k = 1.0 + reach_mm / reach
    return model.with_joints(tuple(replace(j, a=j.a * k, d=j.d * k) for j in model.joints))


def random_cell(
    nominal: RobotModel,
    rng: np.random.Generator,
    *,
    target_offset_mm: tuple[float, float, float] = (25.0, -40.0, 130.0),
    distance_mm: float = 3000.0,
    length_mm: float = 0.3,
    angle_deg: float = 0.03,
) -> TrueCell:
    """A perturbed robot seen by a sensor about ``distance_mm`` away, in a random
    orientation."""
    model = perturbed_model(nominal, rng, length_mm=length_mm, angle_deg=angle_deg)
    T = np.eye(4)
    T[:3, :3] = so3_exp(rng.normal(size=3))
    T[:3, 3] = rng.normal(size=3) / math.sqrt(3) * distance_mm
    return TrueCell(model, np.asarray(target_offset_mm, dtype=np.float64), T)


def random_joints(
    model: RobotModel, rng: np.random.Generator, n: int, *, span: float = 0.8
) -> Array:
    """n joint readings (rad) uniform in the central ``span`` of each joint's range (a
    range wider than a turn counts as one turn each way)."""
    lo, hi = model.limits
    lo = np.maximum(lo, -math.pi)
    hi = np.minimum(hi, math.pi)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * span
    out: Array = rng.uniform(mid - half, mid + half, (n, model.dof))
    return out


def measure(
    cell: TrueCell,
    q: Array,
    rng: np.random.Generator,
    sigma_mm: float,
    conditions: Conditions | None = None,
) -> Array:
    """Positions in the sensor frame with isotropic Gaussian noise (mm)."""
    p = cell.positions(q, conditions)
    out: Array = p + rng.normal(0.0, sigma_mm, p.shape)
    return out


def truth_terms(model: RobotModel, terms: SimulatedTerms) -> tuple[Term, ...]:
    """The simulated robot's errors beyond geometry (``[simulation.terms]``) as error
    terms of its model; one line naming a key that does not fit the robot."""
    n = model.dof
    out: list[Term] = []
    for key, values in (
        ("harmonics_deg", terms.harmonics_deg),
        ("compliance_deg_per_knm", terms.compliance_deg_per_knm),
        ("ratio_pct", terms.ratio_pct),
    ):
        if values and len(values) != n:
            raise InputError(
                f"simulation.terms.{key}: {len(values)} values for a robot of {n} joints "
                "(one a joint, or none)"
            )
    for j, h in enumerate(terms.harmonics_deg, start=1):
        if any(h):
            out.append(Term("harmonics", j, HARMONICS, tuple(math.radians(v) for v in h)))
    if any(terms.compliance_deg_per_knm) and model.mass_model is None:
        raise InputError(
            "simulation.terms.compliance_deg_per_knm needs the robot model's mass model: "
            "mass_kg and com_mm in every [[joint]]"
        )
    for j, c in enumerate(terms.compliance_deg_per_knm, start=1):
        if c:
            out.append(Term("compliance", j, ("tau",), (math.radians(c),)))
    for j, k in enumerate(terms.ratio_pct, start=1):
        if k:  # about the reading zero: the geometry's θ holds where it is centred
            out.append(Term("ratio", j, RATIO, (k / 100.0,)))
    return tuple(out)
