"""Cyclic errors at a transmission's own periods, found in the data.

A gear stage, a harmonic drive's wave generator or a belt turns several times per turn of
the joint; its eccentricity then adds to the joint's angle an error that repeats k times
per turn, at an order k no one can know from the model. With hundreds of poses
(:data:`DENSE_POSES`) the data can say: for each joint, the residual of the geometric
fit seen along that joint's turn (the component of each pose's residual along ∂p/∂θ,
divided by its length) is searched, by least squares against an offset, a scale and the
first two harmonics already in the ``harmonics`` term, for the order k (from
:data:`MIN_ORDER` to :data:`MAX_ORDER`, each with at least :data:`SAMPLES_PER_PERIOD`
poses per period over the measured range and the range at least one period) whose
``sin k·q``, ``cos k·q`` explain most. The order is kept when its F test passes at
:data:`P_VALUE`, divided by the number of orders tried (Bonferroni). A joint may have
more than one stage: the search then goes on with the orders kept among the known
regressors, for up to :data:`MAX_ORDERS_PER_JOINT` orders, each passing the same test
against everything found before it. The ``harmonics`` term then carries ``sin{k}``,
``cos{k}`` of every order kept, and blocked cross-validation judges it as a whole like
any term.
"""

from __future__ import annotations

import math

import numpy as np

from cellcal.calib.error_model import State
from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.observations import Data

DENSE_POSES = 300
MIN_ORDER, MAX_ORDER = 3, 60
SAMPLES_PER_PERIOD = 8
P_VALUE = 1e-3
#: the stages of one joint's transmission searched for, at most
MAX_ORDERS_PER_JOINT = 3
#: a joint whose turn moves the target less than this (mm per rad, median) is not
#: searched (the target on its axis)
MIN_LEVER_MM = 1.0


def _fit_rss(A: Array, s: Array) -> float:
    coef, *_ = np.linalg.lstsq(A, s, rcond=None)
    return float(np.sum((s - A @ coef) ** 2))


def cyclic_orders(state: State, data: Data) -> dict[int, tuple[int, ...]]:
    """Per joint (1-based), the orders of the cyclic errors the geometric fit ``state``
    leaves in ``data``, where they are significant (most significant first); empty for
    fewer than :data:`DENSE_POSES` poses."""
    q = data.q
    N, n = q.shape
    if N < DENSE_POSES:
        return {}
    g = data.groups
    residual = data.residuals(state)[:, :3]
    in_base = np.einsum("nji,nj->ni", state.Rs[g.session], residual)  # Rᵀ r per row
    k = target_kinematics(
        state.model, q, state.target_offsets[g.target], conditions=data.conditions
    )
    found: dict[int, tuple[int, ...]] = {}
    for i in range(n):
        J = k.J_rows[:, :, 5 * i]
        length = np.linalg.norm(J, axis=1)
        if float(np.median(length)) < MIN_LEVER_MM:
            continue
        s = np.sum(J * in_base, axis=1) / length**2  # the turn that fits each residual (rad)
        orders = _orders(q[:, i], s, length)
        if orders:
            found[i + 1] = orders
    return found


def _orders(qi: Array, s: Array, sw: Array) -> tuple[int, ...]:
    """The significant orders of the turns ``s`` (rad) along the readings ``qi``, each
    searched with those found before it among the known regressors; ``sw``: the poses'
    weights (a pose where the turn moves the target more says more)."""
    from scipy.special import fdtrc  # imported when a search runs: scipy.special is slow to load

    N = len(qi)
    span = float(np.ptp(qi))
    base = np.c_[np.ones(N), qi, np.sin(qi), np.cos(qi), np.sin(2 * qi), np.cos(2 * qi)]
    orders = [
        order
        for order in range(MIN_ORDER, MAX_ORDER + 1)
        if order * span >= 2 * math.pi and N / (order * span / (2 * math.pi)) >= SAMPLES_PER_PERIOD
    ]
    kept: list[int] = []
    while orders and len(kept) < MAX_ORDERS_PER_JOINT:
        rss0 = _fit_rss(base * sw[:, None], s * sw)
        dof = N - base.shape[1] - 2
        if dof <= 0:
            break
        best: tuple[float, int] | None = None
        for order in orders:
            A = np.c_[base, np.sin(order * qi), np.cos(order * qi)]
            rss1 = _fit_rss(A * sw[:, None], s * sw)
            F = ((rss0 - rss1) / 2.0) / (rss1 / dof) if rss1 > 0 else math.inf
            p = float(fdtrc(2, dof, F))  # the F distribution's survival function
            if best is None or p < best[0]:
                best = (p, order)
        if best is None or best[0] * len(orders) >= P_VALUE:
            break
        kept.append(best[1])
        orders.remove(best[1])
        base = np.c_[base, np.sin(best[1] * qi), np.cos(best[1] * qi)]
    return tuple(kept)
