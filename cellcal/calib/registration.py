"""Rigid (and similarity) registration of two frames from common points.

``fit_rigid(src, dst)`` returns ``T_dst_src``: ``dst ≈ T_dst_src @ src``. Every method of
the paper's Sec. 3.1/4.3 is here, plus weighted, robust and batched forms. Computation
is in float64 on centred coordinates, so float32 input and coordinates far from the
origin (a tracker 10 km from its datum) lose nothing.

The robust and covariance-weighted loops are in ``registration_weights.py``; the batched
fit and leave-one-out in ``registration_batch.py``.

Size (about 600 lines, over the 500 of the house's rule): what is left is one job — the
public ``fit_rigid``, its input checks, the degenerate-geometry diagnosis and ``RigidFit``
with its statistics — and the solvers' dispatch and the diagnosis read the same private
state; the next cut would be ``RigidFit`` (about 150 lines) into a module of its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.calib import rigid_solvers as rs
from cellcal.calib.characteristic_line import CoincidenceStep, auto_lines, characteristic_line
from cellcal.calib.geometry import Array, skew
from cellcal.errors import (
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MirroredCorrespondenceError,
)

Method = Literal[
    "svd", "quaternion", "three-point", "rodrigues", "rodrigues-linear", "small-angle", "line"
]
METHODS: tuple[str, ...] = (
    "svd",
    "quaternion",
    "three-point",
    "rodrigues",
    "rodrigues-linear",
    "small-angle",
    "line",
)
#: Methods that minimise Σ wᵢ|rᵢ|² (and so take weights, covariances, scale, robust loss).
LEAST_SQUARES_METHODS = frozenset({"svd", "quaternion", "rodrigues", "small-angle"})
Robust = Literal["huber", "tukey", "ransac"]
ROBUST = ("huber", "tukey", "ransac")

#: Relative width (√ of the scatter ratio) under which points count as collinear.
COLLINEAR_TOL = 1e-7
#: ... and under which a warning says the roll about the line is poorly determined.
NEAR_COLLINEAR_WARN = 1e-3
#: Median of the norm of a 3-D standard normal vector (χ with 3 degrees of freedom).
CHI3_MEDIAN = 1.5381722


@dataclass(frozen=True)
class RigidFit:
    """The result of :func:`fit_rigid`. ``T`` maps src coordinates into dst (mm).

    ``residuals`` are ``dst − T(src)`` per point (n×3, mm), ``residual_norms`` their lengths.
    ``rms`` and ``max`` are over the points used in the fit (``inliers``; all points
    unless a robust option rejected some). ``sigma0`` is √(Σ wᵢ|rᵢ|²/dof): mm with unit
    weights, dimensionless (ideally ≈ 1) with weights 1/σ². ``covariance`` is the
    a-posteriori 6×6 covariance of (rotation vector [rad], translation [mm]) of
    ``T = [Exp(ω) R | t]``, first order; it is None for methods that are not least
    squares (three-point, line), whose own uncertainty is larger than that of least squares.
    ``condition`` is the condition number of the rotation block of the normal matrix
    (∞ for collinear points). ``support_points`` lists the point indices a
    point-selecting method used (three-point: one triple; line: lines A and B).
    """

    method: str
    T: Array
    R: Array
    t: Array
    scale: float
    dof: int
    inliers: NDArray[np.bool_]
    iterations: int
    warnings: tuple[str, ...]
    scale_estimated: bool = False
    support_points: tuple[tuple[int, ...], ...] = ()
    line_steps: tuple[CoincidenceStep, ...] = ()
    # What the lazily computed statistics need: centred clouds, their centroids, the
    # weights. Not part of equality.
    _Pc: Array = field(default_factory=lambda: np.zeros((0, 3)), repr=False, compare=False)
    _Qc: Array = field(default_factory=lambda: np.zeros((0, 3)), repr=False, compare=False)
    _qbar: Array = field(default_factory=lambda: np.zeros(3), repr=False, compare=False)
    _pbar: Array = field(default_factory=lambda: np.zeros(3), repr=False, compare=False)
    _w: Array | None = field(default=None, repr=False, compare=False)
    _W: Array | None = field(default=None, repr=False, compare=False)

    @property
    def n(self) -> int:
        return int(self._Pc.shape[0])

    @cached_property
    def residuals(self) -> Array:
        """``dst − T(src)`` per point (n×3, mm), computed on centred coordinates."""
        # Zero up to rounding for least squares; the centroid mismatch of CL / three-point.
        offset = self.scale * (self.R @ self._pbar) + self.t - self._qbar
        r: Array = self._Qc - self.scale * (self._Pc @ self.R.T) - offset
        return r

    @cached_property
    def _sq(self) -> Array:
        r = self.residuals
        sq: Array = np.einsum("ij,ij->i", r, r)
        return sq

    @cached_property
    def _sq_used(self) -> Array:
        sq = self._sq
        return (
            sq if self.dof + (7 if self.scale_estimated else 6) == 3 * len(sq) else sq[self.inliers]
        )

    @cached_property
    def residual_norms(self) -> Array:
        """Length of each residual (mm)."""
        out: Array = np.sqrt(self._sq)
        return out

    @cached_property
    def rms(self) -> float:
        """Root mean square residual length over the inliers (mm)."""
        sq = self._sq_used
        return math.sqrt(float(sq.sum()) / sq.shape[0])

    @cached_property
    def max(self) -> float:
        """Largest residual length among the inliers (mm)."""
        return math.sqrt(float(self._sq_used.max()))

    @cached_property
    def sigma0(self) -> float:
        """√(Σ wᵢ|rᵢ|² / dof) over the inliers; NaN without redundancy."""
        if self.dof <= 0:
            return math.nan
        inl = self.inliers
        if self._W is not None:
            ri = self.residuals[inl]
            ssr = float(np.einsum("ni,nij,nj->", ri, self._W[inl], ri))
        elif self._w is not None and self.method not in ("three-point", "line"):
            ssr = float(self._w[inl] @ self._sq[inl])
        else:
            ssr = float(np.sum(self._sq[inl]))
        return math.sqrt(ssr / self.dof)

    @cached_property
    def _normal(self) -> Array:
        """Normal matrix of (ω, centroid shift[, scale]) at the solution (centred)."""
        from cellcal.calib.registration_weights import _pose_jacobian  # builds on this module

        inl = self.inliers
        Rp = self.scale * (self._Pc[inl] @ self.R.T)
        J = _pose_jacobian(Rp, self.scale_estimated, self.scale)
        m = len(Rp)
        if self._W is not None:
            N: Array = np.einsum("nia,nij,njb->ab", J, self._W[inl], J)
        else:
            w = np.ones(m) if self._w is None else self._w[inl]
            N = np.einsum("n,nia,nib->ab", w, J, J)
        return N

    @cached_property
    def _cov_full(self) -> Array | None:
        if self.method not in LEAST_SQUARES_METHODS or self.dof <= 0:
            return None
        try:
            inv = np.asarray(np.linalg.inv(self._normal), dtype=np.float64)
        except np.linalg.LinAlgError:
            return None
        C: Array = np.asarray(self.sigma0**2 * inv, dtype=np.float64)
        # From (ω, centroid shift) to (ω, t at the dst origin): t = c − Exp(ω) s R p̄.
        G = np.eye(C.shape[0])
        G[3:6, 0:3] = skew(self.scale * (self.R @ self._pbar))
        out: Array = G @ C @ G.T
        return out

    @cached_property
    def covariance(self) -> Array | None:
        """6×6 covariance of (rotation vector [rad], translation [mm]); None if not LS."""
        C = self._cov_full
        return None if C is None else C[:6, :6]

    @cached_property
    def scale_std(self) -> float:
        """Standard uncertainty of the scale (0 when scale is not estimated)."""
        C = self._cov_full
        if C is None or C.shape[0] < 7:
            return 0.0
        return float(np.sqrt(C[6, 6]))

    @cached_property
    def condition(self) -> float:
        """Condition number of the rotation block of the normal matrix (geometry only)."""
        # The rotation block with translation (and scale) eliminated: the Schur
        # complement, independent of where the centroid is taken.
        N = self._normal
        S = N[:3, :3] - N[:3, 3:] @ np.linalg.solve(N[3:, 3:], N[3:, :3])
        ev = np.linalg.eigvalsh(0.5 * (S + S.T))
        return float("inf") if ev[0] <= ev[2] * 1e-15 else float(ev[2] / ev[0])


# --------------------------------------------------------------------------- input checks


def as_points(x: object, name: str) -> Array:
    """An (n, 3) float64 array, or an :class:`InputError` that says what is wrong."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array of numbers ({exc})") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name}: expected an (n, 3) array of points, got shape {a.shape}")
    if not np.isfinite(a).all():
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
        raise InputError(f"{name}: point {bad} is not finite (NaN or inf)")
    return a


def _check_weights(weights: object, n: int) -> Array:
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise InputError(f"weights: expected {n} values, got shape {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise InputError("weights: must be finite and non-negative")
    if np.count_nonzero(w) < 3:
        raise DegenerateGeometryError("weights: fewer than 3 points have a positive weight")
    return w


def _check_cov(cov: object, n: int, name: str) -> Array:
    C = np.asarray(cov, dtype=np.float64)
    if C.shape == (n, 3):  # per-axis standard deviations
        C = np.einsum("ni,ij->nij", C**2, np.eye(3))
    if C.shape != (n, 3, 3):
        raise InputError(f"{name}: expected (n, 3, 3) covariances or (n, 3) σ, got {C.shape}")
    if not np.isfinite(C).all():
        raise InputError(f"{name}: covariances must be finite")
    if not np.allclose(C, np.swapaxes(C, 1, 2), rtol=1e-9, atol=1e-15):
        raise InputError(f"{name}: covariances must be symmetric")
    if (np.linalg.eigvalsh(C)[:, 0] < 0).any():
        raise InputError(f"{name}: covariances must be positive semi-definite")
    return C


def _diagnose_geometry(P: Array, Q: Array, w: Array) -> list[str]:
    """Raise for coincident or collinear clouds; return warnings for nearly collinear ones."""
    warnings: list[str] = []
    use = w > 0
    for name, X in (("src", P[use]), ("dst", Q[use])):
        Xc = X - X.mean(axis=0)
        ev = np.linalg.eigvalsh(Xc.T @ Xc)
        span = float(np.sqrt(max(ev[2], 0.0)))
        scale = max(float(np.max(np.abs(X))), 1.0)

        def distinct(X: Array = X, scale: float = scale) -> int:
            # counted only for the refusal: sorting a million rows takes a second
            return len(np.unique(np.round(X / (1e-9 * scale)), axis=0))

        if span <= 1e-12 * scale:
            raise DegenerateGeometryError(
                f"{name}: all {len(X)} points coincide ({distinct()} distinct); "
                "the transformation is undetermined"
            )
        ratio = float(np.sqrt(max(ev[1], 0.0) / ev[2]))
        if ratio < COLLINEAR_TOL:
            raise DegenerateGeometryError(
                f"{name}: the {len(X)} points are collinear ({distinct()} distinct); "
                "the rotation about their line is undetermined — add a point off the line"
            )
        if ratio < NEAR_COLLINEAR_WARN:
            warnings.append(
                f"{name}: points are nearly collinear (width/length {ratio:.2g}); "
                "the rotation about their line is poorly determined"
            )
    return warnings


def _mirror_check(H: Array, Pc: Array, Qc: Array, w: Array) -> None:
    """Refuse a correspondence that a reflection fits far better than any rotation."""
    U, S, Vt = rs.svd3(H)
    if _det3(U) * _det3(Vt) >= 0 or S[2] <= 1e-9 * S[0]:
        return
    pp = float(np.sum(w[:, None] * Pc * Pc))
    qq = float(np.sum(w[:, None] * Qc * Qc))
    # Best residual with free scale, proper rotation vs reflection (Umeyama).
    e_rot = max(qq - (S[0] + S[1] - S[2]) ** 2 / pp, 0.0)
    e_ref = max(qq - (S[0] + S[1] + S[2]) ** 2 / pp, 0.0)
    if e_ref < 0.25 * e_rot:
        sw = float(w.sum())
        raise MirroredCorrespondenceError(
            "the correspondence is mirrored: a reflection fits it (RMS "
            f"{np.sqrt(e_ref / sw):.4g} mm) far better than any rotation (RMS "
            f"{np.sqrt(e_rot / sw):.4g} mm); one frame is left-handed or an axis is inverted"
        )


# --------------------------------------------------------------------------- solvers


@dataclass(frozen=True)
class _Solution:
    R: Array
    t: Array
    scale: float
    iterations: int = 0
    support: tuple[tuple[int, ...], ...] = ()
    steps: tuple[CoincidenceStep, ...] = ()
    warnings: tuple[str, ...] = ()


def _solve_ls(P: Array, Q: Array, w: Array, method: str, scale: bool) -> _Solution:
    sw = float(w.sum())
    pc = (w @ P) / sw
    qc = (w @ Q) / sw
    Pc = P - pc
    Qc = Q - qc
    H = rs.cross_covariance(Pc, Qc, w)
    if np.linalg.det(H) < 0:
        _mirror_check(H, Pc, Qc, w)
    it = 0
    if method == "svd":
        R = rs.svd_rotation(H)
    elif method == "quaternion":
        R = rs.quaternion_rotation(H)
    elif method == "rodrigues":
        R, it = rs.rodrigues_iterated(Pc, Qc, w)
    elif method == "rodrigues-linear":
        R = rs.rodrigues_linear(Pc, Qc, w)
    else:
        R, it = rs.small_angle_iterated(Pc, Qc, w)
    if method in ("rodrigues", "small-angle"):
        # At the least-squares optimum R·H is symmetric with eigenvalues (S₀, S₁, ±S₂);
        # a stationary point where two are negative is a saddle, not the answer.
        ev = np.linalg.eigvalsh(0.5 * (R @ H + (R @ H).T))
        if ev[0] + ev[1] < -1e-9 * abs(ev[2]):
            raise ConvergenceError(
                f"{method}: the iteration stopped at a saddle point (a rotation about "
                "180° from the answer); use --method svd"
            )
    s = 1.0
    if scale:
        s = float(np.trace(R @ H)) / float(np.sum(w[:, None] * Pc * Pc))
        if s <= 0:
            raise DegenerateGeometryError("scale: the best-fit scale is not positive")
    return _Solution(R, qc - s * (R @ pc), s, it)


def pick_three(P: Array) -> tuple[int, int, int]:
    """A well-spread triple: farthest from the centroid, farthest from it, farthest from
    their line. O(n)."""
    c = P.mean(axis=0)
    i = int(np.argmax(np.sum((P - c) ** 2, axis=1)))
    j = int(np.argmax(np.sum((P - P[i]) ** 2, axis=1)))
    d = (P[j] - P[i]) / np.linalg.norm(P[j] - P[i])
    k = int(np.argmax(np.sum(np.cross(P - P[i], d) ** 2, axis=1)))
    return i, j, k


def _solve_three_point(P: Array, Q: Array, idx: Sequence[int] | None) -> _Solution:
    n = len(P)
    if idx is None:
        i, j, k = pick_three(P)
    else:
        if len(idx) != 3 or len(set(idx)) != 3 or any(x < 0 or x >= n for x in idx):
            raise InputError(f"three-point: need 3 distinct point indices in 0..{n - 1}")
        i, j, k = (int(x) for x in idx)
    for X, name in ((P, "src"), (Q, "dst")):
        a, b = X[j] - X[i], X[k] - X[i]
        area = float(np.linalg.norm(np.cross(a, b)))
        if area <= 1e-12 * max(float(a @ a), float(b @ b), 1e-300):
            raise DegenerateGeometryError(
                f"three-point: points {i}, {j}, {k} are collinear in {name}; choose others"
            )
    Fp = rs.triad_frame(P[j] - P[i], P[k] - P[i])
    Fq = rs.triad_frame(Q[j] - Q[i], Q[k] - Q[i])
    R = Fq @ Fp.T
    sel = [i, j, k]
    t = Q[sel].mean(axis=0) - R @ P[sel].mean(axis=0)
    return _Solution(R, t, 1.0, 0, ((i, j, k),))


def _solve_line(P: Array, Q: Array, lines: tuple[Sequence[int], Sequence[int]] | None) -> _Solution:
    if lines is None:
        la, lb = auto_lines(P)
    else:
        if len(lines) != 2:
            raise InputError("line: give two characteristic lines, A and B")
        la, lb = list(lines[0]), list(lines[1])
    lf = characteristic_line(P, Q, la, lb)
    return _Solution(
        lf.T[:3, :3], lf.T[:3, 3], 1.0, 0, (tuple(la), tuple(lb)), lf.steps, lf.warnings
    )


# --------------------------------------------------------------------------- public API


def fit_rigid(
    src: object,
    dst: object,
    *,
    method: str = "svd",
    weights: object | None = None,
    cov_src: object | None = None,
    cov_dst: object | None = None,
    scale: bool = False,
    robust: str | None = None,
    lines: tuple[Sequence[int], Sequence[int]] | None = None,
    three_points: Sequence[int] | None = None,
    ransac_threshold: float | None = None,
    seed: int = 0,
) -> RigidFit:
    """Fit ``T_dst_src`` (src → dst) from corresponding points, rows matched by index.

    ``method``: ``svd`` (Kabsch/Arun/Umeyama, the default), ``quaternion`` (Horn),
    ``rodrigues`` (Cayley matrix, iterated to convergence), ``rodrigues-linear`` (one
    linear Cayley solve), ``small-angle`` (linearised Helmert, iterated), ``three-point``
    and ``line`` (the paper's characteristic-line method; ``lines=(A, B)`` gives each line
    as two or more point indices, else they are picked automatically).
    ``weights``: per-point weights (1/σ²). ``cov_src``/``cov_dst``: per-point 3×3
    covariances (or n×3 σ) — the fit then minimises the Mahalanobis residual.
    ``scale``: also estimate a uniform scale (Umeyama). ``robust``: ``huber`` or
    ``tukey`` (IRLS) or ``ransac`` (3-point samples; ``ransac_threshold`` in mm, else
    from the least-median sample). The robust and weighted options need a least-squares
    method.
    """
    P = _points(src, "src")
    Q = _points(dst, "dst")
    n = P.shape[0]
    if Q.shape != P.shape:
        raise InputError(f"src has {n} points but dst has {len(Q)}; they must correspond")
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if n < 3:
        raise DegenerateGeometryError(f"need at least 3 common points, got {n}")
    # NaN and inf propagate into the sums: check the whole arrays only if a sum is bad.
    sum_p, sum_q = np.add.reduce(P, 0), np.add.reduce(Q, 0)
    if not math.isfinite(sum(sum_p.tolist()) + sum(sum_q.tolist())):
        as_points(P, "src")
        as_points(Q, "dst")
        raise InputError("coordinates too large: their sum overflows")
    plain = weights is None and cov_src is None and cov_dst is None and robust is None and not scale
    if not plain:
        _check_options(method, weights, cov_src, cov_dst, scale, robust)
    if lines is not None and method != "line":
        raise InputError("lines are only used by the line method")
    if three_points is not None and method != "three-point":
        raise InputError("three_points is only used by the three-point method")
    if ransac_threshold is not None and robust != "ransac":
        raise InputError("ransac_threshold is only used with robust='ransac'")

    C_src = C_dst = None
    w: Array | None = None
    if cov_src is not None or cov_dst is not None:
        C_src = _check_cov(cov_src, n, "cov_src") if cov_src is not None else np.zeros((n, 3, 3))
        C_dst = _check_cov(cov_dst, n, "cov_dst") if cov_dst is not None else np.zeros((n, 3, 3))
        tr = np.trace(C_src, axis1=1, axis2=2) + np.trace(C_dst, axis1=1, axis2=2)
        if (tr <= 0).any():
            raise InputError("covariances: every point needs a non-zero covariance")
        w = 3.0 / tr
    elif weights is not None:
        w = _check_weights(weights, n)

    # Cheap geometry screen through H's singular values; diagnose in detail only if needed.
    warnings: list[str] = []
    pc, qc = sum_p / n, sum_q / n
    Pc, Qc = P - pc, Q - qc
    H = Pc.T @ Qc
    U, Sv, Vt = rs.svd3(H)
    if not Sv[1] > NEAR_COLLINEAR_WARN**2 * Sv[0] or w is not None:
        warnings += _diagnose_geometry(P, Q, np.ones(n) if w is None else w)
    det_uv = _det3(U) * _det3(Vt)
    if det_uv < 0:
        _mirror_check(H, Pc, Qc, np.ones(n))

    inliers: NDArray[np.bool_] | None = None
    W = None
    if method == "three-point":
        sol = _solve_three_point(P, Q, three_points)
    elif method == "line":
        sol = _solve_line(P, Q, lines)
    elif robust in ("huber", "tukey"):
        from cellcal.calib.registration_weights import _irls  # it builds on this module's solvers

        sol, w, inliers = _irls(P, Q, _ones_or(w, n), method, scale, robust)
    elif robust == "ransac":
        from cellcal.calib.ransac import ransac  # it builds on this module's solvers

        sol, w, inliers = ransac(P, Q, _ones_or(w, n), method, scale, ransac_threshold, seed)
    elif method == "svd" and w is None:
        R = rs.rotation_from_svd(U, Vt, det_uv)
        s_ = 1.0
        if scale:
            s_ = float(np.trace(R @ H)) / float(np.vdot(Pc, Pc))
        sol = _Solution(R, qc - s_ * (R @ pc), s_)
    else:
        sol = _solve_ls(P, Q, _ones_or(w, n), method, scale)
    if C_src is not None and C_dst is not None:
        from cellcal.calib.registration_weights import _refine_full_covariance  # as _irls

        sol, W = _refine_full_covariance(P, Q, sol, C_src, C_dst, scale, inliers)
    warnings += sol.warnings

    R, s, t = sol.R, sol.scale, sol.t
    if inliers is not None and w is not None:
        inliers = inliers & (w > 0)
    elif w is not None:
        inliers = w > 0
    if inliers is None or inliers.all():
        inliers = np.ones(n, dtype=bool)
        m = n
    else:
        m = int(np.count_nonzero(inliers))
    if not scale:
        pp, qq = float(np.vdot(Pc, Pc)), float(np.vdot(Qc, Qc))
        if not 0.25 * pp < qq < 4.0 * pp:
            warnings.append(
                f"dst is {math.sqrt(qq / pp):.4g}× the size of src: different units? "
                "(scale=True fits it)"
            )
    T = np.zeros((4, 4))
    T[:3, :3] = R if s == 1.0 else s * R
    T[:3, 3] = t
    T[3, 3] = 1.0
    return RigidFit(
        method=method,
        T=T,
        R=R,
        t=t,
        scale=s,
        dof=3 * m - (7 if scale else 6),
        inliers=inliers,
        iterations=sol.iterations,
        warnings=tuple(warnings),
        scale_estimated=scale,
        support_points=sol.support,
        line_steps=sol.steps,
        _Pc=Pc,
        _Qc=Qc,
        _qbar=qc,
        _pbar=pc,
        _w=w,
        _W=W,
    )


def _points(x: object, name: str) -> Array:
    a = x if isinstance(x, np.ndarray) and x.dtype == np.float64 else None
    if a is None or a.ndim != 2 or a.shape[1] != 3:
        return as_points(x, name)
    return a


def _det3(A: Array) -> float:
    (a, b, c), (d, e, f), (g, h, i) = A.tolist()
    return float(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g))


def _ones_or(w: Array | None, n: int) -> Array:
    return np.ones(n) if w is None else w


def _check_options(
    method: str,
    weights: object | None,
    cov_src: object | None,
    cov_dst: object | None,
    scale: bool,
    robust: str | None,
) -> None:
    if robust is not None and robust not in ROBUST:
        raise InputError(f"unknown robust option {robust!r}; choose one of {', '.join(ROBUST)}")
    ls = method in LEAST_SQUARES_METHODS or method == "rodrigues-linear"
    extras = [
        name
        for name, val in (
            ("weights", weights),
            ("covariances", cov_src if cov_src is not None else cov_dst),
            ("robust", robust),
        )
        if val is not None
    ] + (["scale"] if scale else [])
    if extras and not ls:
        raise InputError(
            f"{method}: the option(s) {', '.join(extras)} require a least-squares method "
            "(svd, quaternion, rodrigues, rodrigues-linear, small-angle)"
        )
    if weights is not None and (cov_src is not None or cov_dst is not None):
        raise InputError("give either weights or covariances, not both")


def apply_fit(fit: RigidFit, points: object) -> Array:
    """Map src points (n×3) into dst with a fit."""
    X = as_points(points, "points")
    out: Array = fit.scale * (X @ fit.R.T) + fit.t
    return out
