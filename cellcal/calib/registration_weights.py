"""Weights and robust loops of the rigid fit (:func:`~cellcal.calib.registration.fit_rigid`).

The pose Jacobian shared by ``RigidFit``'s statistics and the covariance-weighted
Gauss–Newton, the per-point Mahalanobis weights Σᵢ⁻¹ (``cov_src``/``cov_dst``), and the
IRLS loop of the ``huber`` and ``tukey`` robust options. It builds on the solvers of
``registration.py``, which imports it late, inside the functions that need it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from cellcal.calib import rigid_solvers as rs
from cellcal.calib.geometry import Array, so3_exp
from cellcal.calib.registration import (
    CHI3_MEDIAN,
    _diagnose_geometry,
    _Solution,
    _solve_ls,
)
from cellcal.errors import ConvergenceError, DegenerateGeometryError, InputError

HUBER_K = 2.8  # ≈ 95 % quantile of χ₃: points beyond it are down-weighted
TUKEY_C = 4.7  # points beyond it get weight zero


def _pose_jacobian(Rp: Array, with_scale: bool, scale: float) -> Array:
    """∂rᵢ/∂(ω, c[, s]) for rᵢ = qᵢ − (Exp(ω) s R pᵢ + c); ``Rp`` holds s R pᵢ (n×3)."""
    J = np.zeros((len(Rp), 3, 7 if with_scale else 6))
    J[:, 0, 1], J[:, 0, 2] = -Rp[:, 2], Rp[:, 1]
    J[:, 1, 0], J[:, 1, 2] = Rp[:, 2], -Rp[:, 0]
    J[:, 2, 0], J[:, 2, 1] = -Rp[:, 1], Rp[:, 0]
    J[:, :, 3:6] = -np.eye(3)
    if with_scale:
        J[:, :, 6] = -Rp / scale
    return J


def _combined_weights(R: Array, s: float, C_src: Array, C_dst: Array) -> Array:
    """Σᵢ⁻¹ with Σᵢ = C_dstᵢ + s² R C_srcᵢ Rᵀ; a singular Σᵢ is a user error."""
    Sig = C_dst + s * s * np.einsum("ij,njk,lk->nil", R, C_src, R)
    ev = np.linalg.eigvalsh(Sig)
    bad = np.flatnonzero(ev[:, 0] <= 1e-12 * np.maximum(ev[:, 2], 1e-300))
    if len(bad):
        raise InputError(
            f"covariances: point {int(bad[0])} has no uncertainty along some direction "
            "(a zero σ on the same axis in both files); give every point a positive σ"
        )
    W: Array = np.linalg.inv(Sig)
    return W


def _refine_full_covariance(
    P: Array,
    Q: Array,
    sol: _Solution,
    C_src: Array,
    C_dst: Array,
    scale: bool,
    inliers: NDArray[np.bool_] | None,
) -> tuple[_Solution, Array]:
    """Gauss–Newton on (ω, c[, s]) minimising Σ rᵢᵀ Σᵢ⁻¹ rᵢ over the inliers, where
    Σᵢ = C_dst + s² R C_src Rᵀ is re-evaluated each step. Works on centred coordinates
    (a datum kilometres away costs nothing); returns the solution and Σᵢ⁻¹ of every point."""
    use = np.ones(len(P), dtype=bool) if inliers is None else inliers
    pc, qc = P[use].mean(axis=0), Q[use].mean(axis=0)
    Pc, Qc = P[use] - pc, Q[use] - qc
    Cs, Cd = C_src[use], C_dst[use]
    R, s = sol.R, sol.scale
    c = s * (R @ pc) + sol.t - qc  # image of the source centroid, in centred dst coordinates
    cost_prev = math.inf
    for it in range(1, rs.MAX_ITER + 1):
        W = _combined_weights(R, s, Cs, Cd)
        Rp = s * (Pc @ R.T)
        r = Qc - Rp - c
        cost = float(np.einsum("ni,nij,nj->", r, W, r))
        J = _pose_jacobian(Rp, scale, s)
        N = np.einsum("nia,nij,njb->ab", J, W, J)
        g = np.einsum("nia,nij,nj->a", J, W, r)
        dx = -np.linalg.solve(N, g)
        R, c = so3_exp(dx[:3]) @ R, c + dx[3:6]
        if scale:
            s *= 1.0 + dx[6] / s
        small = float(dx[:3] @ dx[:3]) < 1e-26 and float(dx[3:6] @ dx[3:6]) < 1e-20
        stalled = it > 2 and abs(cost_prev - cost) <= 1e-14 * cost
        if small or stalled:
            t = c + qc - s * (R @ pc)
            return _Solution(R, t, s, sol.iterations + it), _combined_weights(R, s, C_src, C_dst)
        cost_prev = cost
    raise ConvergenceError(f"covariance-weighted fit: no convergence in {rs.MAX_ITER} steps")


# --------------------------------------------------------------------------- robust wrappers


def _robust_weights(u: Array, kind: str) -> Array:
    if kind == "huber":
        out: Array = np.minimum(1.0, HUBER_K / np.maximum(u, 1e-300))
        return out
    out = np.where(u < TUKEY_C, (1.0 - (u / TUKEY_C) ** 2) ** 2, 0.0)
    return out


def _irls(
    P: Array, Q: Array, w0: Array, method: str, scale: bool, kind: str
) -> tuple[_Solution, Array, NDArray[np.bool_]]:
    w = w0.copy()
    sol = _solve_ls(P, Q, w, method, scale)
    kinds = ["huber"] if kind == "huber" else ["huber", "tukey"]
    u = np.zeros(len(P))
    total = 0
    for k in kinds:
        for _ in range(rs.MAX_ITER):
            total += 1
            r = np.linalg.norm(Q - sol.scale * (P @ sol.R.T) - sol.t, axis=1)
            sigma = float(np.median(r[w0 > 0])) / CHI3_MEDIAN
            if sigma <= 1e-12 * max(1.0, float(np.max(np.abs(Q)))):
                break  # an exact fit: nothing to down-weight
            u = r / sigma
            w_new = w0 * _robust_weights(u, k)
            if np.count_nonzero(w_new) < 3:
                raise DegenerateGeometryError(
                    f"robust ({kind}): fewer than 3 points left with a positive weight"
                )
            _diagnose_geometry(P, Q, w_new)
            change = float(np.max(np.abs(w_new - w)))
            w = w_new
            sol = _solve_ls(P, Q, w, method, scale)
            if change < 1e-10:
                break
    cut = HUBER_K if kind == "huber" else TUKEY_C
    inl = u <= cut if kind == "huber" else w > 0
    sol = _Solution(sol.R, sol.t, sol.scale, total)
    return sol, w, np.asarray(inl & (w0 > 0))
