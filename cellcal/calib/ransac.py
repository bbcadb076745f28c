"""RANSAC for the rigid fit (``fit_rigid(..., robust="ransac")``), in bounded memory.

Every 3-point sample is fitted with the batched SVD (all C(m, 3) samples when there are
at most :data:`MAX_SAMPLES`, else that many drawn from the seed), and each hypothesis is
scored by MSAC (Torr & Zisserman 2000: inliers cost their squared residual, outliers
the squared threshold; the lowest total wins). The inlier threshold is
``ransac_threshold`` (mm), else :data:`RANSAC_SIGMAS` robust σ of the best sample (its
median residual). The inliers of the best hypothesis are then refitted by least squares
until the set is stable.

Size: the hypotheses are scored on at most :data:`SCORE_ROWS` points — all of them up
to that many, else that many drawn once from the seed — and their residuals are
computed at most :data:`CHUNK_ELEMENTS` at a time, so memory stays about 50 MB however
many rows come in (10⁶ rows once asked for 44.7 GiB). The inliers and the refits use
every row.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.registration import (
    CHI3_MEDIAN,
    _diagnose_geometry,
    _Solution,
    _solve_ls,
)
from cellcal.calib.registration_batch import fit_rigid_batch
from cellcal.errors import DegenerateGeometryError, InputError

#: Default inlier threshold, in robust σ of the best sample.
RANSAC_SIGMAS = 4.0
#: 3-point samples tried (all of them when there are fewer).
MAX_SAMPLES = 2000
#: The hypotheses are scored on at most this many points.
SCORE_ROWS = 10_000
#: Residuals (samples × points) computed at once: 8 MB of float64, 24 MB of predictions.
CHUNK_ELEMENTS = 1_000_000


def _residuals(R: Array, t: Array, s: Array, P: Array, Q: Array) -> Array:
    """|Q − (s R P + t)| for each hypothesis (rows) and point (columns)."""
    pred = np.matmul(P, R.transpose(0, 2, 1)) * s[:, None, None] + t[:, None, :]
    out: Array = np.linalg.norm(Q[None] - pred, axis=2)
    return out


def _per_hypothesis(
    R: Array, t: Array, s: Array, P: Array, Q: Array, reduce: Callable[[Array], Array]
) -> Array:
    """``reduce`` (residual rows → one value each) over every hypothesis, in chunks."""
    step = max(1, CHUNK_ELEMENTS // max(len(P), 1))
    parts = [
        reduce(_residuals(R[b : b + step], t[b : b + step], s[b : b + step], P, Q))
        for b in range(0, len(R), step)
    ]
    out: Array = np.concatenate(parts)
    return out


def ransac(
    P: Array,
    Q: Array,
    w0: Array,
    method: str,
    scale: bool,
    threshold: float | None,
    seed: int,
    max_samples: int = MAX_SAMPLES,
) -> tuple[_Solution, Array, NDArray[np.bool_]]:
    """The fit of the best hypothesis's inliers, their weights (``w0`` on inliers, 0
    elsewhere) and the inlier mask (see the module's notes)."""
    n = len(P)
    rng = np.random.default_rng(seed)
    cand = np.flatnonzero(w0 > 0)
    m = len(cand)
    if m * (m - 1) * (m - 2) // 6 <= max_samples:
        samples = np.array(list(combinations(cand, 3)))
    else:
        samples = np.array([rng.choice(cand, 3, replace=False) for _ in range(max_samples)])
    bs = fit_rigid_batch(P[samples], Q[samples], scale=scale)
    ok = ~(bs.degenerate | bs.mirrored)
    if not ok.any():
        raise DegenerateGeometryError("ransac: every 3-point sample is collinear")
    R, t, s = bs.R[ok], bs.t[ok], bs.scale[ok]
    rows = cand
    if m > SCORE_ROWS:
        rows = np.sort(np.random.default_rng([seed, 1]).choice(cand, SCORE_ROWS, replace=False))
    Ps, Qs = P[rows], Q[rows]
    if threshold is None:
        med = _per_hypothesis(R, t, s, Ps, Qs, lambda r: np.median(r, axis=1))
        best = int(np.argmin(med))
        sigma = float(med[best]) / CHI3_MEDIAN * (1.0 + 5.0 / max(m - 3, 1))
        threshold = max(RANSAC_SIGMAS * sigma, 1e-9 * max(1.0, float(np.max(np.abs(Q)))))
    elif not np.isfinite(threshold) or threshold <= 0:
        raise InputError("ransac threshold must be a positive number of mm")
    cut = float(threshold)
    score = _per_hypothesis(R, t, s, Ps, Qs, lambda r: (np.minimum(r, cut) ** 2).sum(axis=1))
    best = int(np.argmin(score))
    r_best = np.linalg.norm(Q[cand] - s[best] * (P[cand] @ R[best].T) - t[best], axis=1)
    inl = np.zeros(n, dtype=bool)
    inl[cand[r_best <= cut]] = True
    # Refit on the inliers until the set is stable; the set returned is the one fitted.
    for attempt in range(20):
        if inl.sum() < 3:
            raise DegenerateGeometryError("ransac: fewer than 3 inliers")
        w = np.where(inl, w0, 0.0)
        _diagnose_geometry(P, Q, w)
        sol = _solve_ls(P, Q, w, method, scale)
        res = np.linalg.norm(Q - sol.scale * (P @ sol.R.T) - sol.t, axis=1)
        new = (res <= cut) & (w0 > 0)
        if np.array_equal(new, inl) or new.sum() < 3 or attempt == 19:
            break
        inl = new
    return sol, np.where(inl, w0, 0.0), inl
