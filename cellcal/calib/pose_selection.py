"""Fewer poses that identify as well: D-optimal selection on the identification Jacobian.

Each candidate pose k contributes a block G_k (3 × P: the target position's derivatives
with respect to the P identifiable parameters, columns scaled to unit length over all
candidates so that millimetres and radians weigh alike). A set S of poses identifies
the parameters with covariance ∝ (Σ_{k∈S} G_kᵀ G_k)⁻¹; D-optimal sets maximise the
log-determinant of that information matrix, which shrinks the volume of the
parameters' confidence ellipsoid.

The selection is greedy (add the candidate that raises log det most: by the matrix
determinant lemma, log det(I₃ + G_k M⁻¹ G_kᵀ) for every candidate at once), then
Fedorov exchange: swap a chosen pose for a candidate while that raises log det.
Deterministic; numpy only. At least ⌊P/3⌋ + 1 poses: 3N equations must outnumber the P
parameters, or nothing is left to estimate the noise from (the campaign refuses such a
plan too).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.errors import InputError

#: The information matrix starts as this × I (relative to the mean diagonal), so that the
#: first few poses, which cannot determine P parameters yet, still compare.
RIDGE = 1e-9
#: An exchange must raise log det by at least this to be made.
MIN_GAIN = 1e-9


@dataclass(frozen=True)
class PoseSelection:
    """The chosen candidates (indices, in the order chosen), the log-determinant of their
    information matrix, its condition number (√ of the information matrix's, i.e. that
    of the stacked Jacobian), the exchanges made after the greedy pass, and ``history``:
    log det after the greedy pass and after each exchange pass that changed the set
    (non-decreasing)."""

    chosen: tuple[int, ...]
    log_det: float
    condition_number: float
    exchanges: int
    history: tuple[float, ...] = ()


def information(G: Array, rows: Array | list[int]) -> Array:
    """Σ G_kᵀ G_k over ``rows`` (G: K×3×P)."""
    g = G[np.asarray(rows, dtype=np.intp)]
    out: Array = np.einsum("kip,kiq->pq", g, g)
    return out


def _gains(G: Array, M_inv: Array) -> Array:
    """log det(I + G_k M⁻¹ G_kᵀ) for every candidate k."""
    S = np.einsum("kip,pq,kjq->kij", G, M_inv, G) + np.eye(3)
    sign, logdet = np.linalg.slogdet(S)
    out: Array = np.where(sign > 0, logdet, -np.inf)
    return out


def _logdet(M: Array) -> float:
    sign, value = np.linalg.slogdet(M)
    return float(value) if sign > 0 else -np.inf


def d_optimal(G: Array, n: int, *, max_passes: int = 20) -> PoseSelection:
    """``n`` of the K candidates (G: K×3×P, scaled) that maximise log det Σ G_kᵀ G_k."""
    G = np.asarray(G, dtype=np.float64)
    if G.ndim != 3 or G.shape[1] != 3 or not np.isfinite(G).all():
        raise InputError("the candidates' Jacobian must be finite, K × 3 × P")
    K, _, P = G.shape
    if n > K:
        raise InputError(f"{n} poses asked for, {K} reachable candidates")
    if 3 * n <= P:
        raise InputError(
            f"{n} poses give {3 * n} equations for {P} identifiable parameters; "
            f"choose at least {P // 3 + 1}"
        )
    scale = float(np.mean(np.einsum("kip,kip->p", G, G))) / K
    ridge = RIDGE * scale * np.eye(P)
    chosen: list[int] = []
    free = np.ones(K, dtype=bool)
    M = ridge.copy()
    for _ in range(n):
        gains = np.where(free, _gains(G, np.linalg.inv(M)), -np.inf)
        k = int(np.argmax(gains))
        chosen.append(k)
        free[k] = False
        M = M + G[k].T @ G[k]
    exchanges = 0
    history = [_logdet(information(G, chosen))]
    for _ in range(max_passes):
        improved = False
        for slot in range(n):
            out = chosen[slot]
            M_without = M - G[out].T @ G[out]
            gains = np.where(free, _gains(G, np.linalg.inv(M_without)), -np.inf)
            k = int(np.argmax(gains))
            current = _logdet(M) - _logdet(M_without)
            if gains[k] > current + MIN_GAIN:
                chosen[slot] = k
                free[k], free[out] = False, True
                M = M_without + G[k].T @ G[k]
                exchanges += 1
                improved = True
        if not improved:
            break
        history.append(_logdet(information(G, chosen)))
    info = information(G, chosen)
    eig = np.linalg.eigvalsh(info)
    cond = float(np.sqrt(eig[-1] / eig[0])) if eig[0] > 0 else float("inf")
    return PoseSelection(tuple(chosen), _logdet(info), cond, exchanges, tuple(history))


def nearest_neighbour_order(q: Array, start: Array) -> tuple[int, ...]:
    """An order of the poses ``q`` (N×n, rad) that keeps moves short: from ``start``,
    always to the nearest pose not yet visited (largest joint move)."""
    left = list(range(len(q)))
    order: list[int] = []
    here = np.asarray(start, dtype=np.float64)
    while left:
        d = np.abs(q[left] - here).max(axis=1)
        k = left.pop(int(np.argmin(d)))
        order.append(k)
        here = q[k]
    return tuple(order)
