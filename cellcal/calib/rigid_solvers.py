"""Rotation solvers for centred, weighted correspondences.

Each solver takes centred source points ``P`` and destination points ``Q`` (n×3, the
weighted centroids already removed) and per-point weights ``w`` (n,), and returns the
rotation ``R`` that maps ``P`` onto ``Q`` and the number of iterations it took. The
least-squares ones (SVD, quaternion, iterated Cayley, iterated small-angle) all reach
the same minimiser of ``Σ wᵢ |qᵢ − R pᵢ|²``; they differ in how they get there.

References: Arun, Huang & Blostein 1987 and Umeyama 1991 (SVD); Horn 1987 (unit
quaternion); Cayley / Gibbs vector, the "Rodrigo matrix" of the paper (Rodrigues
parameters); linearised Helmert (small-angle) iterated on SO(3).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from cellcal.calib.geometry import Array, so3_exp
from cellcal.errors import ConvergenceError

#: Iterative solvers stop when the rotation update is below this angle (rad).
ANGLE_TOL = 1e-14
MAX_ITER = 100


def cross_covariance(P: Array, Q: Array, w: Array) -> Array:
    """``H = Σ wᵢ pᵢ qᵢᵀ`` (3×3)."""
    H: Array = (P * w[:, None]).T @ Q
    return H


@functools.cache
def _dgesvd() -> Callable[..., Any]:
    # loaded at the first registration: scipy.linalg takes 0.3 s of CPU to import, which
    # a twin or a service that has not yet registered anything need not pay
    from scipy.linalg.lapack import dgesvd

    return dgesvd  # type: ignore[no-any-return]


def svd3(H: Array) -> tuple[Array, Array, Array]:
    """SVD of a 3×3 matrix, ``H = U diag(S) Vt``, through LAPACK's dgesvd.

    scipy's public LAPACK wrapper costs about 4 µs here against 10 µs for
    ``numpy.linalg.svd``, whose Python-level checks dominate at this size; the
    registration of 80 points spends a quarter of its time in this one call."""
    U, S, Vt, info = _dgesvd()(H)
    if info != 0:
        raise ConvergenceError(f"SVD did not converge (LAPACK info {info})")
    return U, S, Vt


def svd_rotation(H: Array) -> Array:
    """Kabsch / Arun with the reflection fix: the proper rotation maximising tr(R H)."""
    U, _, Vt = svd3(H)
    return rotation_from_svd(U, Vt)


def rotation_from_svd(U: Array, Vt: Array, det_uv: float | None = None) -> Array:
    """``R = V diag(1, 1, det(V Uᵀ)) Uᵀ`` from the SVD ``H = U S Vᵀ``; ``det_uv`` is
    det(U)·det(Vᵀ) = det(V Uᵀ) when the caller already has it."""
    R: Array = Vt.T @ U.T
    if det_uv is None:
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        det_uv = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if det_uv < 0.0:
        Vt = Vt.copy()
        Vt[2] *= -1.0
        R = Vt.T @ U.T
    return R


def quaternion_rotation(H: Array) -> Array:
    """Horn (1987): the unit quaternion is the top eigenvector of a symmetric 4×4 matrix."""
    Sxx, Sxy, Sxz = H[0]
    Syx, Syy, Syz = H[1]
    Szx, Szy, Szz = H[2]
    N = np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )
    _, vecs = np.linalg.eigh(N)
    q0, qx, qy, qz = vecs[:, 3]
    return np.array(
        [
            [
                q0 * q0 + qx * qx - qy * qy - qz * qz,
                2 * (qx * qy - q0 * qz),
                2 * (qx * qz + q0 * qy),
            ],
            [
                2 * (qy * qx + q0 * qz),
                q0 * q0 - qx * qx + qy * qy - qz * qz,
                2 * (qy * qz - q0 * qx),
            ],
            [
                2 * (qz * qx - q0 * qy),
                2 * (qz * qy + q0 * qx),
                q0 * q0 - qx * qx - qy * qy + qz * qz,
            ],
        ]
    )


def cayley(u: Array) -> Array:
    """The Cayley ("Rodrigo") matrix ``(I − [u]×)⁻¹ (I + [u]×)``: rotation by 2·atan|u| about u."""
    uu = float(u @ u)
    x, y, z = u
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    out: Array = ((1.0 - uu) * np.eye(3) + 2.0 * np.outer(u, u) + 2.0 * K) / (1.0 + uu)
    return out


def _cayley_step(P: Array, Q: Array, w: Array) -> tuple[Array, float]:
    """One linear Cayley solve, ``q − p = u × (q + p)`` in the weighted least-squares
    sense; returns u and the condition number of its normal matrix."""
    S = P + Q
    ws = w[:, None] * S
    M = float(np.sum(ws * S)) * np.eye(3) - ws.T @ S
    rhs = 2.0 * np.sum(w[:, None] * np.cross(P, Q), axis=0)
    ev = np.linalg.eigvalsh(M)
    cond = float(ev[2] / ev[0]) if ev[0] > 0 else float("inf")
    u: Array = np.linalg.lstsq(M, rhs, rcond=None)[0]
    return u, cond


_FLIPS = (
    np.eye(3),
    np.diag([1.0, -1.0, -1.0]),
    np.diag([-1.0, 1.0, -1.0]),
    np.diag([-1.0, -1.0, 1.0]),
)
#: A Cayley normal matrix worse conditioned than this means a rotation near 180°.
_CAYLEY_MAX_COND = 1e8


def rodrigues_linear(P: Array, Q: Array, w: Array) -> Array:
    """One-shot Cayley solve. Cayley parameters are infinite at 180° (and the linear
    system singular there), so the source is also pre-turned by 180° about each
    coordinate axis and the candidate with the smallest, well-determined residual
    rotation is kept: one of the four is always at most about 120° from the answer."""
    best: tuple[float, Array] | None = None
    for F in _FLIPS:
        u, cond = _cayley_step(P @ F.T, Q, w)
        if cond > _CAYLEY_MAX_COND:
            continue
        uu = float(u @ u)
        if best is None or uu < best[0]:
            best = (uu, cayley(u) @ F)
        if uu <= 1.0:  # residual rotation ≤ 90°: well inside Cayley's range
            break
    if best is None:
        raise ConvergenceError("rodrigues: the linear Cayley system is singular")
    return best[1]


def _step_tolerance(cond: float) -> float:
    """Smallest meaningful rotation update: rounding in a solve grows with its condition."""
    return ANGLE_TOL * max(1.0, cond)


def rodrigues_iterated(P: Array, Q: Array, w: Array) -> tuple[Array, int]:
    """Cayley solve repeated on the residual rotation until it vanishes; the fixed point
    satisfies ``Σ wᵢ (R pᵢ) × qᵢ = 0``, the least-squares stationarity condition."""
    R = rodrigues_linear(P, Q, w)
    for it in range(1, MAX_ITER + 1):
        u, cond = _cayley_step(P @ R.T, Q, w)
        R = cayley(u) @ R
        if float(u @ u) < (_step_tolerance(cond) / 2.0) ** 2:
            return R, it
    raise ConvergenceError(f"rodrigues: no convergence in {MAX_ITER} iterations; use --method svd")


def small_angle_iterated(
    P: Array, Q: Array, w: Array, R0: Array | None = None
) -> tuple[Array, int]:
    """Linearised Helmert transformation (``R ≈ I + [ω]×``) solved by Gauss–Newton on SO(3).

    Each step solves ``Σ wᵢ (|pᵢ|² I − pᵢ pᵢᵀ) ω = Σ wᵢ pᵢ × qᵢ`` for the rotated source
    and applies the exact exponential. Converges from the identity for rotations well
    beyond the 5° where a single linear step is accurate; exactly at 180° it may not
    start, and says so rather than return a wrong answer."""
    R = np.eye(3) if R0 is None else R0
    for it in range(1, MAX_ITER + 1):
        Pr = P @ R.T
        wp = w[:, None] * Pr
        M = float(np.sum(wp * Pr)) * np.eye(3) - wp.T @ Pr
        rhs = np.sum(w[:, None] * np.cross(Pr, Q), axis=0)
        ev = np.linalg.eigvalsh(M)
        cond = float(ev[2] / ev[0]) if ev[0] > 0 else float("inf")
        omega: Array = np.linalg.lstsq(M, rhs, rcond=None)[0]
        R = so3_exp(omega) @ R
        if float(omega @ omega) < _step_tolerance(cond) ** 2:
            return R, it
    raise ConvergenceError(
        f"small-angle: no convergence in {MAX_ITER} iterations (the points are nearly "
        "collinear, or the frames are turned by about 180°); use --method svd"
    )


def triad_frame(v1: Array, v2: Array) -> Array:
    """Orthonormal frame (columns) with first axis along ``v1`` and ``v2`` in the 1–2 plane."""
    e1 = v1 / np.linalg.norm(v1)
    e3 = np.cross(e1, v2)
    e3 /= np.linalg.norm(e3)
    e2 = np.cross(e3, e1)
    return np.column_stack([e1, e2, e3])
