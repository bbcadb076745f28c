"""Which noise-hidden parameters to free after all: chosen by k-fold held-out error.

:func:`cellcal.calib.identifiability.weakly_determined` leaves at nominal every
parameter whose standard uncertainty exceeds a manufacturing tolerance. That rule keeps a
fit from "identifying" absurd values (a real UR5: α5 −27°, d5 +54 mm), but it is blind to
what a parameter does for the prediction: on a real Barrett WAM it left six wrist
parameters at nominal and the held-out error rose from 3.26 to 3.66 mm.

Here the data decide, within the plausible. Greedily, each parameter the rule left out
is tried back in (the rule then re-applied to the rest, since freeing one changes the
others' uncertainty); a candidate set counts only if its fit on all the data passes the
acceptance checks (every correction within manufacturing tolerance), and it is taken
only if it lowers the k-fold error — the RMS of each fold's poses predicted by a fit to
the other folds — by more than :data:`GAIN`. The folds are regions of the workspace
(:func:`cellcal.calib.blocked_cv.region_folds`: seeded, so the choice is repeatable),
which ask what a parameter does where it was not fitted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib import levenberg
from cellcal.calib.blocked_cv import region_folds
from cellcal.calib.error_model import ParameterSpec, State
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import Identifiability, weakly_determined
from cellcal.calib.observations import Data
from cellcal.errors import CellcalError

FOLDS = 5
#: A parameter is freed only if it lowers the k-fold error by more than this fraction.
GAIN = 0.01
#: Equations per parameter a fold's fit needs at least.
EQUATIONS_PER_PARAMETER = 3


@dataclass(frozen=True)
class Choice:
    """The outcome: ``ident`` with the freed parameters identified again; ``freed``
    their names; ``rule_mm`` and ``chosen_mm`` the k-fold RMS (weighted units: mm for
    unit weights) of the rule's set and of the chosen one; ``tried``: (name, k-fold RMS
    or NaN when its fit failed, plausible) of every candidate."""

    @property
    def tempting(self) -> tuple[tuple[str, float], ...]:
        """Candidates refused as implausible whose k-fold error beat the chosen set's,
        each once with its lowest error (a candidate is tried again in every round)."""
        best: dict[str, float] = {}
        for n, cv, ok in self.tried:
            if not ok and cv < self.chosen_mm * (1.0 - GAIN):
                best[n] = min(cv, best.get(n, cv))
        return tuple(best.items())

    ident: Identifiability
    freed: tuple[str, ...]
    rule_mm: float
    chosen_mm: float
    tried: tuple[tuple[str, float, bool], ...]


def kfold_rms(
    state: State,
    sel: tuple[ParameterSpec, ...],
    data: Data,
    w: Array,
    folds: int = FOLDS,
    labels: NDArray[np.intp] | None = None,
) -> float:
    """RMS (per pose, weighted) of each fold's residuals predicted by a fit of ``sel`` to
    the other folds. The fits are Gauss–Newton steps from ``state`` (a fit to all the
    poses) on the other folds' normal equations — one pass over the poses for all folds,
    exact to first order: removing a fifth of the poses moves the solution by about its
    uncertainty, where the model is linear to far below the noise."""
    parts = levenberg.linearise_folds(state, sel, data, w, folds, labels=labels)
    G = sum(p.G for p in parts)
    g = sum(p.g for p in parts)
    total = 0.0
    for p in parts:
        train = levenberg.Linearisation(G - p.G, g - p.g, 0.0)
        delta = levenberg.solve_step(train)
        # the fold's residuals after the step: r − J·δ
        total += p.cost - 2.0 * float(delta @ p.g) + float(delta @ p.G @ delta)
    return math.sqrt(max(total, 0.0) / max(len(data.q), 1))


def choose(
    ident: Identifiability,
    point_R: Array,
    sigma0: float,
    state: State,
    data: Data,
    w: Array,
    plausible: Callable[[State, tuple[ParameterSpec, ...]], bool],
) -> Choice:
    """Free, greedily, the weak parameters of ``ident`` that lower the k-fold error and
    keep the fit plausible. ``point_R``/``sigma0``: as for ``weakly_determined`` (the
    first fit over the exact-rank set); ``state``: the fit of the rule's set;
    ``plausible(state, sel)``: whether a fit passes the acceptance checks."""
    specs = ident.specs
    base = _exact_rank(ident)

    def selection(keep: tuple[int, ...]) -> Identifiability:
        return weakly_determined(point_R, sigma0, base, spare=keep)

    def chosen_specs(i: Identifiability) -> tuple[ParameterSpec, ...]:
        return tuple(specs[k] for k in i.identified)

    regions = region_folds(state, data)
    folds, labels = len(regions.train), regions.label

    def cv(st: State, sel: tuple[ParameterSpec, ...]) -> float:
        return kfold_rms(st, sel, data, w, folds, labels)

    current = ident
    best = cv(state, chosen_specs(current))
    rule = best
    kept: tuple[int, ...] = ()
    tried: list[tuple[str, float, bool]] = []
    n_train = len(data.q) - math.ceil(len(data.q) / FOLDS)
    while current.weak:
        step: tuple[float, Identifiability, State, int] | None = None
        for cand in current.weak:
            trial = selection((*kept, cand))
            sel = chosen_specs(trial)
            if n_train * w.shape[1] < EQUATIONS_PER_PARAMETER * len(sel):
                continue
            try:
                full = levenberg.fit(state, sel, data, w, tol=levenberg.COARSE).state
                ok = plausible(full, sel)
                err = cv(full, sel)
            except CellcalError:
                ok, err = False, math.nan
            tried.append((specs[cand].name, err, ok))
            if ok and err < best * (1.0 - GAIN) and (step is None or err < step[0]):
                step = (err, trial, full, cand)
        if step is None:
            break
        best, current, state, cand = step
        kept += (cand,)
    freed = tuple(specs[k].name for k in kept)
    return Choice(current, freed, rule, best, tuple(tried))


def _exact_rank(ident: Identifiability) -> Identifiability:
    """``ident`` before any parameter was left out as weak."""
    identified = tuple(sorted(ident.identified + ident.weak))
    others = tuple(i for i in ident.unidentifiable if i not in ident.weak)
    return Identifiability(
        specs=ident.specs,
        identified=identified,
        unidentifiable=others,
        condition_number=ident.condition_number,
        correlated=ident.correlated,
        remaining=ident.remaining,
        weak=(),
        fixed=ident.fixed,
    )
