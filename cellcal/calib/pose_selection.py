"""Fewer poses that identify as well: D- and I-optimal selection on the identification
Jacobian.

Each candidate pose k contributes a block G_k (3 × P: the target position's derivatives
with respect to the P identifiable parameters, columns scaled to unit length over all
candidates so that millimetres and radians weigh alike). A set S of poses identifies
the parameters with covariance ∝ (Σ_{k∈S} G_kᵀ G_k)⁻¹; D-optimal sets maximise the
log-determinant of that information matrix, which shrinks the volume of the
parameters' confidence ellipsoid.

The selection is greedy (add the candidate that raises log det most: by the matrix
determinant lemma, log det(I₃ + G_k M⁻¹ G_kᵀ) for every candidate at once), then
Fedorov exchange: swap a chosen pose for a candidate while that raises log det.
I-optimal sets minimise instead the mean prediction variance at workspace points whose
3 × P blocks are H_j: trace(A M⁻¹) with A = mean_j H_jᵀ H_j, i.e. the expected squared
error of the calibrated model's prediction there, in units of the measurement noise σ².
That is what the held-out error measures; D-optimality only shrinks the parameters'
uncertainty, and near-equal D-optimal sets can predict outside the cube very
differently. The search starts from the D-optimal set and exchanges poses while the
mean variance falls; each exchange is a rank-6 update of M, scored for every candidate
at once by the Woodbury identity.

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
#: A selection's time grows as chosen × candidates (each greedy step and each exchange
#: scores every candidate): at most this much of it, refused before it starts (about a
#: minute for 250 of 8000 candidates, I-optimal).
SELECTION_BUDGET = 2_000_000


@dataclass(frozen=True)
class PoseSelection:
    """The chosen candidates (indices), the log-determinant of their information matrix,
    its condition number (√ of the information matrix's, i.e. that of the stacked
    Jacobian), the exchanges made, and ``history``: the criterion at the start (after
    the greedy pass for D, the D-optimal set for I) and after each exchange pass that
    changed the set (log det, non-decreasing; mean prediction variance, non-increasing).
    ``criterion`` is ``D`` or ``I``; ``prediction_rms``, where the workspace points were
    given, is √(mean prediction variance): the expected RMS error of the prediction
    there in units of the measurement noise σ."""

    chosen: tuple[int, ...]
    log_det: float
    condition_number: float
    exchanges: int
    history: tuple[float, ...] = ()
    criterion: str = "D"
    prediction_rms: float = float("nan")


def information(G: Array, rows: Array | list[int]) -> Array:
    """Σ G_kᵀ G_k over ``rows`` (G: K×3×P)."""
    g = G[np.asarray(rows, dtype=np.intp)]
    out: Array = np.einsum("kip,kiq->pq", g, g)
    return out


def _gains(G: Array, M_inv: Array) -> Array:
    """log det(I + G_k M⁻¹ G_kᵀ) for every candidate k."""
    S = (G @ M_inv) @ np.swapaxes(G, 1, 2) + np.eye(3)
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
    if n * K > SELECTION_BUDGET:
        raise InputError(
            f"{n} poses of {K} candidates: at most {SELECTION_BUDGET // K} from that many "
            f"(the selection's work grows as chosen × candidates, bounded at "
            f"{SELECTION_BUDGET:,})"
        )
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
    log_det, cond = _volume(G, chosen)
    return PoseSelection(tuple(chosen), log_det, cond, exchanges, tuple(history))


def _volume(G: Array, chosen: list[int]) -> tuple[float, float]:
    """log det and condition number (of the stacked Jacobian) of the chosen poses."""
    info = information(G, chosen)
    eig = np.linalg.eigvalsh(info)
    cond = float(np.sqrt(eig[-1] / eig[0])) if eig[0] > 0 else float("inf")
    return _logdet(info), cond


def workspace_weights(H: Array, P: int) -> Array:
    """A = mean_j H_jᵀ H_j for the workspace points' blocks H (J×3×P, scaled as G)."""
    H = np.asarray(H, dtype=np.float64)
    if H.ndim != 3 or H.shape[1:] != (3, P) or len(H) == 0 or not np.isfinite(H).all():
        raise InputError(f"the workspace points' Jacobian must be finite, J × 3 × {P}, J ≥ 1")
    out: Array = np.einsum("kip,kiq->pq", H, H) / len(H)
    return out


def mean_variance(M: Array, A: Array) -> float:
    """trace(A M⁻¹): the mean prediction variance (σ² units); inf if M is singular."""
    try:
        return float(np.trace(np.linalg.solve(M, A)))
    except np.linalg.LinAlgError:
        return float("inf")


def prediction_rms(G: Array, H: Array, chosen: tuple[int, ...] | list[int]) -> float:
    """√(mean prediction variance) at the workspace points H of the chosen poses of G."""
    value = mean_variance(information(G, list(chosen)), workspace_weights(H, G.shape[2]))
    return float(np.sqrt(value)) if np.isfinite(value) and value >= 0 else float("inf")


def _swap_values(G: Array, M_inv: Array, B: Array, out: int) -> Array:
    """trace(A M'⁻¹) − trace(A M⁻¹) for M' = M − g_outᵀ g_out + G_kᵀ G_k, every k, by the
    Woodbury identity with U_k = [G_k; g_out] and C = diag(I₃, −I₃); +inf where M' is
    singular. ``B`` = M⁻¹ A M⁻¹."""
    K = len(G)
    U = np.concatenate([G, np.broadcast_to(G[out], (K, 3, G.shape[2]))], axis=1)  # K×6×P
    C_inv = np.diag([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])
    Ut = np.swapaxes(U, 1, 2)
    S = C_inv + (U @ M_inv) @ Ut
    T = (U @ B) @ Ut
    delta = np.full(K, np.inf)
    # |det S| = det M' / det M: a swap that shrinks the information volume a billionfold
    # leaves M' (numerically) singular
    ok = np.abs(np.linalg.det(S)) > 1e-9
    if ok.any():
        delta[ok] = -np.trace(np.linalg.solve(S[ok], T[ok]), axis1=1, axis2=2)
    return delta


def i_optimal(G: Array, H: Array, n: int, *, max_passes: int = 20) -> PoseSelection:
    """``n`` of the K candidates (G: K×3×P, scaled) that minimise the mean prediction
    variance at the workspace points H (J×3×P, scaled as G): Fedorov exchange from the
    D-optimal set."""
    start = d_optimal(G, n, max_passes=max_passes)
    G = np.asarray(G, dtype=np.float64)
    A = workspace_weights(H, G.shape[2])
    chosen = list(start.chosen)
    free = np.ones(len(G), dtype=bool)
    free[chosen] = False
    M = information(G, chosen)
    value = mean_variance(M, A)
    if not np.isfinite(value):
        raise InputError("the D-optimal poses do not determine the parameters")
    history = [value]
    exchanges = 0
    for _ in range(max_passes):
        improved = False
        for slot in range(n):
            M_inv = np.asarray(np.linalg.inv(M), dtype=np.float64)
            B: Array = M_inv @ A @ M_inv
            delta = _swap_values(G, M_inv, B, chosen[slot])
            delta[~free] = np.inf
            k = int(np.argmin(delta))
            if delta[k] < -MIN_GAIN * value:
                out = chosen[slot]
                chosen[slot] = k
                free[k], free[out] = False, True
                M = M - G[out].T @ G[out] + G[k].T @ G[k]
                value = mean_variance(M, A)
                exchanges += 1
                improved = True
        if not improved:
            break
        history.append(value)
    log_det, cond = _volume(G, chosen)
    return PoseSelection(
        tuple(chosen),
        log_det,
        cond,
        start.exchanges + exchanges,
        tuple(history),
        "I",
        float(np.sqrt(value)),
    )


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
