"""Forward kinematics of a target point and its derivatives, batched over poses.

Everything is vectorised over N poses with numpy: a campaign's few thousand poses cost
a few milliseconds, where a per-pose loop (through Pinocchio or otherwise) would pay
the Python call overhead N times. The tests check these positions against Pinocchio.

The derivatives are those of the target position (base frame, mm) with respect to the
five elementary geometric parameters of each row — θ, d, a, α, β, in that order — and
to the target offset in the flange frame. Each is the classic screw expression: a
rotation δ about a unit axis u through o moves the point p by δ·u × (p − o); a
translation along u moves it by δ·u.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_terms import (
    ChainFrames,
    Conditions,
    apply_drift,
    drift_of,
    drift_parts,
    drift_variable,
    joint_deltas,
    needs_frames,
)
from cellcal.calib.geometry import Array
from cellcal.calib.robot_model import RobotModel

#: Order of the elementary parameters of each row in the Jacobian.
ROW_PARAMS = ("theta", "d", "a", "alpha", "beta")


@dataclass(frozen=True)
class TargetKinematics:
    """Positions ``p`` (N×3, base frame, mm), flange rotations ``R_flange`` (N×3×3),
    ``J_rows`` (N×3×5n): ∂p/∂(θ, d, a, α, β) of every row (mm/rad, mm/mm), and the joint
    axes ``axes`` (N×3×n, unit vectors in the base frame). ∂p/∂θᵢ is ∂p/∂(angle i); with
    the model's reading map A, ∂p/∂q = ∂p/∂θ · A."""

    p: Array
    R_flange: Array
    J_rows: Array
    axes: Array
    #: ∂(flange orientation)/∂(θ, d, a, α, β) of every row as angular velocities (N×3×5n,
    #: base frame, rad/rad; zero for d and a)
    W_rows: Array | None = None
    #: every link's frame and joint axis (with ``frames=True``)
    frames: ChainFrames | None = None


def chain_frames(model: RobotModel, q: Array) -> ChainFrames:
    """Every link's frame and joint axis at readings ``q``, of the geometry alone."""
    k = target_kinematics(model.geometry, q, np.zeros(3), jacobian=False, frames=True)
    assert k.frames is not None
    return k.frames


def target_kinematics(
    model: RobotModel,
    q: Array,
    target_offset: Array,
    *,
    jacobian: bool = True,
    angular: bool = False,
    conditions: Conditions | None = None,
    frames: bool = False,
) -> TargetKinematics:
    """Target positions for joint readings ``q`` (N×n, rad) and target offset ``target_offset`` (mm;
    one offset, or one per pose: N×3); with ``jacobian`` their derivatives, and with
    ``angular`` also those of the flange orientation (``W_rows``). A model's error terms
    are included, at ``conditions`` (None: the calibration's payload, the campaign's
    start); ``frames``: also return every link's frame (``frames``)."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    N, n = q.shape
    if n != model.dof:
        raise ValueError(f"q has {n} joints, the model {model.dof}")
    angles = model.joint_angles(q)
    if model.terms:
        chain = chain_frames(model, q) if needs_frames(model.terms) else None
        angles = angles + joint_deltas(model.terms, q, chain, model.mass_model, conditions)
    collected: list[tuple[Array, ...]] = []
    x = np.zeros((N, 3))
    y = np.zeros((N, 3))
    z = np.zeros((N, 3))
    x[:, 0] = y[:, 1] = z[:, 2] = 1.0
    o = np.zeros((N, 3))
    # Per row: (axis, origin) pairs for θ, α, β and directions for d, a.
    rec: list[tuple[Array, ...]] = []
    dh = model.convention == "dh"
    for i, jt in enumerate(model.joints):
        ang = jt.theta + angles[:, i]
        c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
        ca, sa = np.cos(jt.alpha), np.sin(jt.alpha)
        cb, sb = np.cos(jt.beta), np.sin(jt.beta)
        if dh:
            # Rz(θ+q): about z through o.
            z_th, o_th = z, o
            x1 = c * x + s * y
            y1 = -s * x + c * y
            z1 = z
            d_dir = z1
            a_dir = x1
            o3 = o + jt.d * z1 + jt.a * x1
            al_axis, al_org = x1, o3
            y4 = ca * y1 + sa * z1
            z4 = -sa * y1 + ca * z1
            be_axis, be_org = y4, o3
            x, y, z = cb * x1 - sb * z4, y4, sb * x1 + cb * z4
            o = o3
        else:
            al_axis, al_org = x, o
            ya = ca * y + sa * z
            za = -sa * y + ca * z
            be_axis, be_org = ya, o
            xb = cb * x - sb * za
            zb = sb * x + cb * za
            yb = ya
            a_dir = xb
            oc = o + jt.a * xb
            z_th, o_th = zb, oc
            x, y, z = c * xb + s * yb, -s * xb + c * yb, zb
            d_dir = zb
            o = oc + jt.d * zb
        if jacobian:
            rec.append((z_th, o_th, d_dir, a_dir, al_axis, al_org, be_axis, be_org))
        if frames:
            collected.append((np.stack([x, y, z], axis=2), o, z_th, o_th))
    R = np.stack([x, y, z], axis=2)
    target_offset = np.asarray(target_offset, dtype=np.float64)
    p = o + (
        R @ target_offset if target_offset.ndim == 1 else np.einsum("nij,nj->ni", R, target_offset)
    )
    chained = None
    if frames:
        chained = ChainFrames(*(np.stack([c[k] for c in collected], axis=1) for k in range(4)))
    drift = drift_of(model.terms)
    grow = None
    p_geometry = p
    if drift is not None:
        grow = 1.0 + drift_parts(drift)[1] * drift_variable(drift, conditions, N)
        p = apply_drift(p, drift, conditions)
    if not jacobian:
        return TargetKinematics(
            p=p,
            R_flange=R,
            J_rows=np.zeros((N, 3, 0)),
            axes=np.zeros((N, 3, 0)),
            frames=chained,
        )
    # θ, α and β turn about an axis through a point: ∂p = axis × (p − point), all rows at
    # once; d and a move along a direction.
    turns = [(0, 0, 1), (3, 4, 5), (4, 6, 7)]  # (column in the row, axis, point) of rec
    axis = np.stack([r[a] for r in rec for _, a, _ in turns], axis=2)  # N×3×3n
    arm = p_geometry[:, :, None] - np.stack([r[o] for r in rec for _, _, o in turns], axis=2)
    cross = np.empty_like(axis)
    cross[:, 0] = axis[:, 1] * arm[:, 2] - axis[:, 2] * arm[:, 1]
    cross[:, 1] = axis[:, 2] * arm[:, 0] - axis[:, 0] * arm[:, 2]
    cross[:, 2] = axis[:, 0] * arm[:, 1] - axis[:, 1] * arm[:, 0]
    rows = np.arange(n)
    J = np.empty((N, 3, 5 * n))
    W = np.zeros((N, 3, 5 * n)) if angular else None
    for k, (col, _, _) in enumerate(turns):
        J[:, :, 5 * rows + col] = cross[:, :, k::3]
        if W is not None:
            W[:, :, 5 * rows + col] = axis[:, :, k::3]
    del arm, cross
    J[:, :, 5 * rows + 1] = np.stack([r[2] for r in rec], axis=2)
    J[:, :, 5 * rows + 2] = np.stack([r[3] for r in rec], axis=2)
    axes = np.ascontiguousarray(axis[:, :, 0::3])
    if grow is not None:
        J *= grow[:, None, None]
    return TargetKinematics(p=p, R_flange=R, J_rows=J, axes=axes, W_rows=W, frames=chained)


def flange_transforms(model: RobotModel, q: Array) -> Array:
    """T_base_flange (N×4×4) for joint readings ``q`` (N×n, rad)."""
    k = target_kinematics(model, q, np.zeros(3), jacobian=False)
    T = np.zeros((len(k.p), 4, 4))
    T[:, :3, :3] = k.R_flange
    T[:, :3, 3] = k.p
    T[:, 3, 3] = 1.0
    return T
