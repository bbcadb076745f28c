"""Inverse kinematics of the target pose, batched over poses (damped least squares).

Used to turn a plan's Cartesian cube into joint readings. Each pose is solved for the
target point's position and the flange's orientation; orientation errors are weighted
by a length so that 1 mrad counts like 0.5 mm at the default 500 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.rotations import rotvec_from_matrix


@dataclass(frozen=True)
class IKSolution:
    """Joint readings (N×n, rad), and per pose: converged, within the joint limits, and
    the remaining position (mm) and orientation (rad) errors."""

    q: Array
    converged: NDArray[np.bool_]
    within_limits: NDArray[np.bool_]
    position_error: Array
    orientation_error: Array

    @property
    def ok(self) -> NDArray[np.bool_]:
        out: NDArray[np.bool_] = self.converged & self.within_limits
        return out


def solve(
    model: RobotModel,
    target_offset: Array,
    p_target: Array,
    R_target: Array,
    q_seed: Array,
    *,
    length_mm: float = 500.0,
    max_iter: int = 200,
    tol_mm: float = 1e-7,
    conditions: Conditions | None = None,
) -> IKSolution:
    """Joint readings that put the target at ``p_target`` (N×3, mm) with the flange at
    ``R_target`` (N×3×3), starting from ``q_seed`` (n or N×n, rad)."""
    p_target = np.atleast_2d(np.asarray(p_target, dtype=np.float64))
    N = len(p_target)
    R_target = np.broadcast_to(np.asarray(R_target, dtype=np.float64), (N, 3, 3))
    q = np.array(np.broadcast_to(np.asarray(q_seed, dtype=np.float64), (N, model.dof)))
    lam = 1e-3
    done = np.zeros(N, dtype=bool)
    ep = np.full(N, np.inf)
    er = np.full(N, np.inf)
    offsets = np.asarray(target_offset, dtype=np.float64)
    active = np.arange(N)  # the poses not yet solved: a solved pose no longer moves
    for _ in range(max_iter):
        qa = q[active]
        k = target_kinematics(
            model,
            qa,
            offsets[active] if offsets.ndim == 2 else offsets,
            conditions=None if conditions is None else conditions.subset(active),
        )
        e_pos = p_target[active] - k.p
        e_rot = rotvec_from_matrix(R_target[active] @ np.swapaxes(k.R_flange, 1, 2))
        ep[active] = np.linalg.norm(e_pos, axis=1)
        er[active] = np.linalg.norm(e_rot, axis=1)
        now = (ep[active] < tol_mm) & (er[active] * length_mm < tol_mm)
        done[active] = now
        go = ~now
        if not go.any():
            break
        J = np.concatenate([k.J_rows[go][:, :, 0::5], k.axes[go] * length_mm], axis=1)  # N×6×n
        J = J @ model.reading_matrix  # ∂/∂angles → ∂/∂readings
        e = np.concatenate([e_pos[go], e_rot[go] * length_mm], axis=1)
        A = J @ np.swapaxes(J, 1, 2) + (lam * length_mm) ** 2 * np.eye(6)
        step = np.einsum("nji,nj->ni", J, np.linalg.solve(A, e[:, :, None])[:, :, 0])
        # Limit a step to 0.3 rad per joint: far from the answer the model is not linear.
        scale = np.minimum(1.0, 0.3 / np.maximum(np.abs(step).max(axis=1), 1e-300))
        active = active[go]
        q[active] = qa[go] + step * scale[:, None]
    q, within = within_limits(model, q)
    return IKSolution(q, done, within, ep, er)


def within_limits(model: RobotModel, q: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Each joint brought within one turn of its limits' centre where that helps, and
    whether every joint of each pose is within its limits."""
    lo, hi = model.limits
    q = np.array(q, dtype=np.float64)
    for j in range(model.dof):
        if math.isfinite(lo[j]) and math.isfinite(hi[j]):
            centre = (lo[j] + hi[j]) / 2
            q[:, j] = centre + (q[:, j] - centre + math.pi) % (2 * math.pi) - math.pi
    inside: NDArray[np.bool_] = np.asarray(((q >= lo - 1e-12) & (q <= hi + 1e-12)).all(axis=1))
    return q, inside
