"""The batched rigid fit and leave-one-out.

:func:`fit_rigid_batch` solves B independent least-squares (SVD) problems at once (the
samples of RANSAC, Monte Carlo runs); :func:`leave_one_out` predicts each point from a
fit to all the others, as one batched problem for plain SVD, else a loop over
:func:`~cellcal.calib.registration.fit_rigid`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.registration import COLLINEAR_TOL, apply_fit, as_points, fit_rigid
from cellcal.errors import DegenerateGeometryError, InputError


@dataclass(frozen=True)
class LeaveOneOut:
    """Prediction error of each point by a fit to all the others (mm).

    ``errors`` is n×3 (NaN where the method could not fit without that point, e.g. a
    point that defines a characteristic line); ``rms`` is over the finite ones.
    """

    errors: Array
    norms: Array
    rms: float
    skipped: int


@dataclass(frozen=True)
class RigidFitBatch:
    """Many least-squares fits at once (SVD): ``R`` (B×3×3), ``t`` (B×3), ``scale`` (B,),
    ``rms`` and ``max`` (B,); ``degenerate`` (B,) marks problems whose points are collinear
    or coincident in either cloud, ``mirrored`` (B,) those a reflection fits far better
    than a rotation, as :func:`fit_rigid` would refuse them; their R, t are not meaningful."""

    R: Array
    t: Array
    scale: Array
    rms: Array
    max: Array
    degenerate: NDArray[np.bool_]
    mirrored: NDArray[np.bool_]

    @property
    def T(self) -> Array:
        B = len(self.R)
        out = np.zeros((B, 4, 4))
        out[:, :3, :3] = self.R * self.scale[:, None, None]
        out[:, :3, 3] = self.t
        out[:, 3, 3] = 1.0
        return out


def fit_rigid_batch(src: object, dst: object, *, scale: bool = False) -> RigidFitBatch:
    """Least-squares (SVD) fits of B independent problems at once: src, dst are B×n×3."""
    try:
        P = np.asarray(src, dtype=np.float64)
        Q = np.asarray(dst, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"batch: not arrays of numbers ({exc})") from None
    if P.ndim != 3 or P.shape[2] != 3 or P.shape != Q.shape:
        raise InputError(f"batch: expected two (B, n, 3) arrays, got {P.shape} and {Q.shape}")
    if P.shape[1] < 3:
        raise DegenerateGeometryError(f"batch: need at least 3 points, got {P.shape[1]}")
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise InputError("batch: points must be finite")
    pc = P.mean(axis=1)
    qc = Q.mean(axis=1)
    Pc = P - pc[:, None, :]
    Qc = Q - qc[:, None, :]
    PcT = np.swapaxes(Pc, 1, 2)
    H = PcT @ Qc
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    Vt[:, 2, :] *= d[:, None]
    R = np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)
    pp = np.einsum("bni,bni->b", Pc, Pc)
    qq = np.einsum("bni,bni->b", Qc, Qc)
    s = (S[:, 0] + S[:, 1] + d * S[:, 2]) / np.maximum(pp, 1e-300) if scale else np.ones(len(P))
    t = qc - s[:, None] * np.einsum("bij,bj->bi", R, pc)
    res = Qc - s[:, None, None] * (Pc @ np.swapaxes(R, 1, 2))
    sq = np.einsum("bni,bni->bn", res, res)
    # Collinear or coincident points in either cloud (eigenvalues of the scatter matrices).
    ev_p = np.linalg.eigvalsh(PcT @ Pc)
    ev_q = np.linalg.eigvalsh(np.swapaxes(Qc, 1, 2) @ Qc)
    tol2 = COLLINEAR_TOL**2
    degenerate = ~((ev_p[:, 1] > tol2 * ev_p[:, 2]) & (ev_q[:, 1] > tol2 * ev_q[:, 2]))
    # Mirrored: the reflection fits far better than the proper rotation (as in fit_rigid).
    with np.errstate(divide="ignore", invalid="ignore"):
        e_rot = qq - (S[:, 0] + S[:, 1] - S[:, 2]) ** 2 / pp
        e_ref = qq - (S[:, 0] + S[:, 1] + S[:, 2]) ** 2 / pp
        mirrored = (d < 0) & (S[:, 2] > 1e-9 * S[:, 0]) & (e_ref < 0.25 * e_rot)
    return RigidFitBatch(
        R=R,
        t=t,
        scale=s,
        rms=np.sqrt(sq.mean(axis=1)),
        max=np.sqrt(sq.max(axis=1)),
        degenerate=degenerate,
        mirrored=mirrored,
    )


#: leave_one_out refits once per point (O(n²) memory for the batched SVD path).
LOO_MAX_POINTS = 5000


def leave_one_out(src: object, dst: object, **kwargs: object) -> LeaveOneOut:
    """Predict each point from a fit to all the others (same method and options).

    With the plain SVD method this runs as one batched problem. Point indices given for
    ``lines`` or ``three_points`` are remapped; a point that one of them needs cannot be
    left out, and its error is NaN (counted in ``skipped``).
    """
    P = as_points(src, "src")
    Q = as_points(dst, "dst")
    n = len(P)
    if Q.shape != P.shape:
        raise InputError(f"src has {n} points but dst has {len(Q)}; they must correspond")
    if n < 4:
        raise DegenerateGeometryError(f"leave-one-out needs at least 4 points, got {n}")
    if n > LOO_MAX_POINTS:
        raise InputError(f"leave-one-out refits once per point: at most {LOO_MAX_POINTS}, got {n}")
    errors = np.full((n, 3), np.nan)
    keep = ~np.eye(n, dtype=bool)
    options = [v for k, v in kwargs.items() if k not in ("method", "seed")]
    plain = all(v is None or v is False for v in options)
    if plain and kwargs.get("method", "svd") == "svd":
        idx = np.array([np.flatnonzero(row) for row in keep])
        b = fit_rigid_batch(P[idx], Q[idx])
        pred = np.einsum("bij,bj->bi", b.R, P) + b.t
        errors = Q - pred
        errors[b.degenerate | b.mirrored] = np.nan
    else:
        for i in range(n):
            others = np.flatnonzero(keep[i])
            remap = {int(j): k for k, j in enumerate(others)}
            kw = dict(kwargs)
            try:
                for key in ("lines", "three_points"):
                    spec = kw.get(key)
                    if spec is None:
                        continue
                    if key == "lines":
                        kw[key] = tuple([remap[int(j)] for j in g] for g in spec)  # type: ignore[attr-defined]
                    else:
                        kw[key] = [remap[int(j)] for j in spec]  # type: ignore[attr-defined]
                for key in ("weights", "cov_src", "cov_dst"):
                    if kw.get(key) is not None:
                        kw[key] = np.asarray(kw[key])[others]
                f = fit_rigid(P[others], Q[others], **kw)  # type: ignore[arg-type]
            except (KeyError, DegenerateGeometryError):
                continue
            errors[i] = Q[i] - apply_fit(f, P[i : i + 1])[0]
    norms = np.linalg.norm(errors, axis=1)
    ok = np.isfinite(norms)
    rms = float(np.sqrt(np.mean(norms[ok] ** 2))) if ok.any() else float("nan")
    return LeaveOneOut(errors=errors, norms=norms, rms=rms, skipped=int((~ok).sum()))
