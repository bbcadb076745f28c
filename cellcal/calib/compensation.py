"""Compensated targets: the joints that bring the real robot's target to intended points.

The calibrated model is the best knowledge of where the robot really puts its target;
inverse kinematics of that model gives the joints to command. The controller still
computes with its nominal model, so for a controller that takes Cartesian targets the
same joints are handed over as the pose the *nominal* model gives them (its flange pose
at the compensated joints): commanding that pose makes the controller go to these joints.

A target with an orientation is solved for position and orientation (flange in the
base frame). A target without one is solved for its position alone, by damped least
squares from a seed (the joints the program uses today, when given): the least joint
motion from the seed, so the seed chooses the configuration (elbow, wrist) and, in
effect, the orientation.

An answer that cannot be right is refused, per target, with why (``kind``): joints
outside the limits, the flange or the target inside the robot's base (the column
around joint 1's axis below the shoulder), or joints far from the nominal model's own
solution for the point — a compensation corrects manufacturing errors, a few tenths of
a millimetre: at most :data:`MAX_CORRECTION_MM` of correction and
:data:`MAX_JOINT_CHANGE_DEG` on any joint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.inverse_kinematics import solve, within_limits
from cellcal.calib.kinematics import flange_transforms, target_kinematics
from cellcal.calib.robot_model import RobotModel

#: A compensated pose must put the calibrated model's target this close to the point.
REACHED_MM = 1e-6
#: A compensation is small: the nominal model at the compensated joints misses the
#: point by at most this (mm; manufacturing tolerances, as the calibration's acceptance
#: checks), and no joint is turned more than this (deg) from the nominal solution.
MAX_CORRECTION_MM = 10.0
MAX_JOINT_CHANGE_DEG = 5.0
#: The robot's base: the column around joint 1's axis, from the shoulder's height (joint
#: 2's axis) down, out to half the shoulder's distance from the axis and at least this
#: far (mm) — the part of the base no pose of the arm can be in, whatever its size.
BASE_MIN_RADIUS_MM = 100.0
#: ``Compensation.kind`` of a target: reached; not reached (no convergence); and the
#: answers that cannot be right.
REACHED, UNREACHED, LIMITS, BASE, FAR = "", "unreached", "limits", "base", "far"


@dataclass(frozen=True)
class Compensation:
    """Per target: the joints to command (N×n, rad); whether each was solved within the
    joint limits and ``why_not`` otherwise; the calibrated model's remaining distance to
    the point (mm); the nominal model's flange pose at those joints (N×4×4, base frame,
    mm: the Cartesian target for a controller that computes with its nominal model); and
    ``correction_mm``: how far the nominal model places the target at those joints from
    the intended point, which is the size of the compensation; ``kind``: why a target is
    not ok."""

    q: Array
    ok: NDArray[np.bool_]
    why_not: tuple[str, ...]
    residual_mm: Array
    T_base_flange_nominal: Array
    correction_mm: Array
    #: per target: REACHED, UNREACHED (the solver did not get there), or LIMITS, BASE,
    #: FAR (an answer that cannot be right)
    kind: tuple[str, ...] = ()


def _position_only(
    model: RobotModel,
    target_offset: Array,
    p_target: Array,
    q_seed: Array,
    *,
    damping_mm: float = 1.0,
    max_iter: int = 300,
    tol_mm: float = 1e-8,
    conditions: Conditions | None = None,
) -> tuple[Array, NDArray[np.bool_], Array]:
    """Damped least squares on the position alone (3 equations for n joints): each
    step is the least joint motion that reduces the error, so the answer stays near the
    seed. Returns joints, converged, remaining error (mm)."""
    q = np.array(q_seed, dtype=np.float64)
    A = model.reading_matrix
    err = np.full(len(q), np.inf)
    done = np.zeros(len(q), dtype=bool)
    for _ in range(max_iter):
        k = target_kinematics(model, q, target_offset, conditions=conditions)
        e = p_target - k.p
        err = np.linalg.norm(e, axis=1)
        done = err < tol_mm
        if done.all():
            break
        J = k.J_rows[:, :, 0::5] @ A  # N×3×n, mm/rad
        M = J @ np.swapaxes(J, 1, 2) + damping_mm**2 * np.eye(3)
        step = np.einsum("nji,nj->ni", J, np.linalg.solve(M, e[:, :, None])[:, :, 0])
        # Far from the answer the model is not linear: at most 0.3 rad per joint a step.
        scale = np.minimum(1.0, 0.3 / np.maximum(np.abs(step).max(axis=1), 1e-300))
        q = q + np.where(done[:, None], 0.0, step * scale[:, None])
    return q, done, err


def base_column(model: RobotModel) -> tuple[Array, Array, float, float]:
    """The robot's base as a column: a point on joint 1's axis and its direction (base
    frame, at the zero readings), the shoulder's height along it (where joint 2's axis
    comes closest) and the column's radius (half the shoulder's distance from the axis,
    at least :data:`BASE_MIN_RADIUS_MM`)."""

    def axis(i: int) -> tuple[Array, Array]:
        # DH: joint i turns about z of frame i−1; modified DH: about z of frame i.
        k = i - 1 if model.convention == "dh" else i
        if k == 0:
            return np.zeros(3), np.array([0.0, 0.0, 1.0])
        sub = RobotModel(model.name, model.convention, model.joints[:k])
        T = flange_transforms(sub, np.zeros((1, k)))[0]
        return T[:3, 3], T[:3, 2]

    o1, u1 = axis(1)
    if model.dof < 2:
        return o1, u1, 0.0, BASE_MIN_RADIUS_MM
    o2, u2 = axis(2)
    c = np.cross(u1, u2)
    if float(np.linalg.norm(c)) < 1e-9:
        shoulder = o2
    else:  # the point of axis 2 nearest axis 1
        n = np.cross(u1, c)
        shoulder = o2 + u2 * float(np.dot(o1 - o2, n) / np.dot(u2, n))
    w = shoulder - o1
    h = float(np.dot(w, u1))
    radius = max(0.5 * float(np.linalg.norm(w - h * u1)), BASE_MIN_RADIUS_MM)
    return o1, u1, h, radius


def inside_base(model: RobotModel, points: Array) -> NDArray[np.bool_]:
    """Which points (N×3, mm, base frame) are inside the robot's base column
    (:func:`base_column`): nearer joint 1's axis than its radius, on the base's side of
    the shoulder."""
    o1, u1, h, radius = base_column(model)
    w = np.atleast_2d(points) - o1
    t = w @ u1
    r = np.linalg.norm(w - t[:, None] * u1, axis=1)
    below = t * math.copysign(1.0, h) < abs(h) if h != 0.0 else np.zeros(len(w), bool)
    out: NDArray[np.bool_] = np.asarray(below & (r < radius))
    return out


def _solve(
    model: RobotModel,
    target_offset: Array,
    p: Array,
    R: Array | None,
    seed: Array,
    conditions: Conditions | None = None,
) -> tuple[Array, NDArray[np.bool_]]:
    if R is None:
        q, converged, _ = _position_only(model, target_offset, p, seed, conditions=conditions)
        return q, converged
    sol = solve(model, target_offset, p, R, seed, tol_mm=1e-8, conditions=conditions)
    return sol.q, sol.converged


def _verdict(
    calibrated: RobotModel,
    nominal: RobotModel,
    target_offset: Array,
    q: Array,
    q_nom: Array,
    nominal_ok: NDArray[np.bool_],
    correction: Array,
) -> list[tuple[str, str]]:
    """Per target, (kind, why) of an answer that cannot be right, or ("", "")."""
    lo, hi = calibrated.limits
    T = flange_transforms(calibrated, q)
    flange = T[:, :3, 3]
    target = flange + T[:, :3, :3] @ target_offset
    in_base = inside_base(nominal, flange) | inside_base(nominal, target)
    change = np.degrees(np.abs(q - q_nom))
    out: list[tuple[str, str]] = []
    for k in range(len(q)):
        bad = np.flatnonzero((q[k] < lo - 1e-12) | (q[k] > hi + 1e-12))
        if len(bad):
            j = int(bad[0])
            out.append(
                (
                    LIMITS,
                    f"joint {j + 1} at {math.degrees(q[k, j]):.1f}° is outside the joint "
                    f"limits {math.degrees(lo[j]):.6g}..{math.degrees(hi[j]):.6g}°",
                )
            )
        elif in_base[k]:
            which = "flange" if inside_base(nominal, flange[k])[0] else "target"
            where = np.round(flange[k] if which == "flange" else target[k], 1).tolist()
            out.append((BASE, f"its {which} would be inside the robot's base, at {where} mm"))
        elif correction[k] > MAX_CORRECTION_MM:
            out.append(
                (
                    FAR,
                    f"the nominal model misses it by {correction[k]:.3g} mm at these "
                    f"joints (a correction of at most {MAX_CORRECTION_MM:g} mm)",
                )
            )
        elif nominal_ok[k] and change[k].max() > MAX_JOINT_CHANGE_DEG:
            j = int(np.argmax(change[k]))
            out.append(
                (
                    FAR,
                    f"joint {j + 1} is {change[k, j]:.3g}° from the nominal model's "
                    f"solution (at most {MAX_JOINT_CHANGE_DEG:g}°)",
                )
            )
        else:
            out.append((REACHED, ""))
    return out


def compensate(
    calibrated: RobotModel,
    target_offset: Array,
    nominal: RobotModel,
    p_base: Array,
    R_base: Array | None,
    q_seed: Array,
    conditions: Conditions | None = None,
) -> Compensation:
    """Joints that put the calibrated model's target (offset ``target_offset``, mm) at ``p_base``
    (N×3, mm, base frame) with the flange at ``R_base`` (N×3×3) when given, starting
    from ``q_seed`` (N×n, rad); ``nominal``: the controller's model, for the Cartesian
    form, the correction (with the same target offset, so that the correction is the
    kinematic one alone) and the solution the answer must stay near. A target is ok
    when it is reached within the joint limits, outside the robot's base and near the
    nominal solution (``kind``, ``why_not`` say otherwise). A calibrated model's error
    terms (gravity, compliance, harmonics, drift) are part of where it puts the target,
    at ``conditions`` (the payload each target is reached with; None: the
    calibration's payload, the campaign's start)."""
    p_base = np.atleast_2d(np.asarray(p_base, dtype=np.float64))
    seed = np.array(np.broadcast_to(q_seed, (len(p_base), calibrated.dof)), dtype=np.float64)
    q, converged = _solve(calibrated, target_offset, p_base, R_base, seed, conditions)
    q, _ = within_limits(calibrated, q)  # each joint within a turn of its range
    reached = target_kinematics(
        calibrated, q, target_offset, jacobian=False, conditions=conditions
    ).p
    residual = np.linalg.norm(reached - p_base, axis=1)
    got = converged & (residual <= REACHED_MM)
    # The nominal model's own solution from the same seed: the answer must stay near it.
    q_nom, nominal_ok = _solve(nominal, target_offset, p_base, R_base, seed)
    q_nom = q_nom + np.round((q - q_nom) / (2 * np.pi)) * 2 * np.pi  # the same turn
    at_nominal = target_kinematics(nominal, q, target_offset, jacobian=False).p
    correction = np.linalg.norm(at_nominal - p_base, axis=1)
    verdict = _verdict(calibrated, nominal, target_offset, q, q_nom, nominal_ok, correction)
    kind = tuple(v[0] if got[k] else UNREACHED for k, v in enumerate(verdict))
    why = tuple(
        verdict[k][1]
        if got[k]
        else f"the solver did not reach the point ({residual[k]:.3g} mm left)"
        for k in range(len(p_base))
    )
    return Compensation(
        q=q,
        ok=np.array([k == REACHED for k in kind]),
        why_not=why,
        residual_mm=residual,
        T_base_flange_nominal=flange_transforms(nominal, q),
        correction_mm=correction,
        kind=kind,
    )
