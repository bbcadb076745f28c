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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.inverse_kinematics import solve, within_limits
from cellcal.calib.kinematics import flange_transforms, target_kinematics
from cellcal.calib.robot_model import RobotModel

#: A compensated pose must put the calibrated model's target this close to the point.
REACHED_MM = 1e-6


@dataclass(frozen=True)
class Compensation:
    """Per target: the joints to command (N×n, rad); whether each was solved within the
    joint limits and ``why_not`` otherwise; the calibrated model's remaining distance to
    the point (mm); the nominal model's flange pose at those joints (N×4×4, base frame,
    mm: the Cartesian target for a controller that computes with its nominal model); and
    ``correction_mm``: how far the nominal model places the target at those joints from
    the intended point, which is the size of the compensation."""

    q: Array
    ok: NDArray[np.bool_]
    why_not: tuple[str, ...]
    residual_mm: Array
    T_base_flange_nominal: Array
    correction_mm: Array


def _position_only(
    model: RobotModel,
    tool: Array,
    p_target: Array,
    q_seed: Array,
    *,
    damping_mm: float = 1.0,
    max_iter: int = 300,
    tol_mm: float = 1e-8,
) -> tuple[Array, NDArray[np.bool_], Array]:
    """Damped least squares on the position alone (3 equations for n joints): each
    step is the least joint motion that reduces the error, so the answer stays near the
    seed. Returns joints, converged, remaining error (mm)."""
    q = np.array(q_seed, dtype=np.float64)
    A = model.reading_matrix
    err = np.full(len(q), np.inf)
    done = np.zeros(len(q), dtype=bool)
    for _ in range(max_iter):
        k = target_kinematics(model, q, tool)
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


def compensate(
    calibrated: RobotModel,
    tool: Array,
    nominal: RobotModel,
    p_base: Array,
    R_base: Array | None,
    q_seed: Array,
) -> Compensation:
    """Joints that put the calibrated model's target (offset ``tool``, mm) at ``p_base``
    (N×3, mm, base frame) with the flange at ``R_base`` (N×3×3) when given, starting
    from ``q_seed`` (N×n, rad); ``nominal``: the controller's model, for the Cartesian
    form and the correction (with the same target offset, so that the correction is the
    kinematic one alone)."""
    p_base = np.atleast_2d(np.asarray(p_base, dtype=np.float64))
    seed = np.array(np.broadcast_to(q_seed, (len(p_base), calibrated.dof)), dtype=np.float64)
    if R_base is None:
        q, converged, _ = _position_only(calibrated, tool, p_base, seed)
    else:
        sol = solve(calibrated, tool, p_base, R_base, seed, tol_mm=1e-8)
        q, converged = sol.q, sol.converged
    q, inside = within_limits(calibrated, q)
    reached = target_kinematics(calibrated, q, tool, jacobian=False).p
    residual = np.linalg.norm(reached - p_base, axis=1)
    ok = converged & inside & (residual <= REACHED_MM)
    why = tuple(
        ""
        if good
        else (
            "no joint solution within the limits"
            if not inside[k] and converged[k]
            else f"the solver did not reach the point ({residual[k]:.3g} mm left)"
        )
        for k, good in enumerate(ok)
    )
    at_nominal = target_kinematics(nominal, q, tool, jacobian=False).p
    return Compensation(
        q=q,
        ok=np.asarray(ok),
        why_not=why,
        residual_mm=residual,
        T_base_flange_nominal=flange_transforms(nominal, q),
        correction_mm=np.linalg.norm(at_nominal - p_base, axis=1),
    )
