"""Which error terms beyond geometry a calibration adds: only those that held-out data
say improve its predictions.

``--terms auto`` starts from the geometric fit and adds, greedily, the term that most
lowers the blocked cross-validation error (:mod:`cellcal.calib.blocked_cv`: whole
regions of the workspace left out; for ``drift``, later stretches of the campaign) —
only while the gain, pose by pose, is more than :data:`Z_ACCEPT` standard errors from
zero and more than :data:`GAIN` of the error. ``--terms LIST`` fits the listed terms
without the gate and reports each one's cross-validation all the same (the listed set
against the set without it). Every term not added says why.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from cellcal.calib import levenberg
from cellcal.calib.blocked_cv import (
    REGIONS,
    Comparison,
    Folds,
    compare,
    held_out_errors,
    region_folds,
    stretch_folds,
)
from cellcal.calib.cyclic_search import cyclic_orders
from cellcal.calib.error_model import ParameterSpec, State, term_specs
from cellcal.calib.error_terms import (
    DRIFT,
    HARMONICS,
    RATIO,
    TERM_NAMES,
    Term,
    compliance_regressors,
    cyclic,
    gravity_regressors,
    joint_deltas,
    joint_regressors,
)
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import analyse, weakly_determined
from cellcal.calib.kinematics import chain_frames
from cellcal.calib.observations import Data
from cellcal.calib.parameter_choice import EQUATIONS_PER_PARAMETER
from cellcal.errors import CellcalError, InputError

#: A term is accepted when its pose-by-pose gain is this many standard errors from zero …
Z_ACCEPT = 2.0
#: … and lowers the held-out RMS by more than this fraction.
GAIN = 0.01
#: A temperature that changes less than this (°C) over the measurements cannot carry a
#: drift: the time does.
MIN_TEMPERATURE_SPREAD_C = 0.5
#: A joint term that turns its joint farther than this (deg) at any measured pose is no
#: transmission's or deflection's error: refused as implausible.
TERM_LIMIT_DEG = 2.0


#: The mode of a request that fits given terms and judges nothing: a k-fold validation's
#: folds refit the terms their calibration accepted (not a user's choice).
FIXED = "fixed"


@dataclass(frozen=True)
class TermRequest:
    """``auto``, ``geometric``, ``list`` with the listed names, or :data:`FIXED`."""

    mode: str
    names: tuple[str, ...] = ()


def parse_terms(text: str) -> TermRequest:
    """``auto``, ``geometric`` or a comma list of :data:`TERM_NAMES`."""
    t = text.strip()
    if t in ("auto", "geometric"):
        return TermRequest(t)
    names = tuple(dict.fromkeys(n.strip() for n in t.split(",") if n.strip()))
    bad = [n for n in names if n not in TERM_NAMES]
    if bad or not names:
        raise InputError(
            f"--terms {text!r}: choose auto, geometric, or a comma list of {', '.join(TERM_NAMES)}"
        )
    return TermRequest("list", tuple(n for n in TERM_NAMES if n in names))


@dataclass(frozen=True)
class TermVerdict:
    """A term's outcome: accepted or not, why, and its blocked cross-validation (the
    model without it against the model with it; None when it could not be fitted)."""

    name: str
    accepted: bool
    reason: str
    comparison: Comparison | None = None


@dataclass(frozen=True)
class TermChoice:
    """The request's mode, each term's verdict (in :data:`TERM_NAMES` order), and the
    blocked cross-validation RMS (mm, over regions) of the geometric and final models."""

    mode: str
    verdicts: tuple[TermVerdict, ...]
    geometric_cv_mm: float
    final_cv_mm: float

    @property
    def accepted(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.verdicts if v.accepted)

    @property
    def rejected(self) -> dict[str, str]:
        return {v.name: v.reason for v in self.verdicts if not v.accepted}


def candidates(name: str, state: State, data: Data) -> tuple[Term, ...] | str:
    """The terms (zero coefficients) ``name`` adds to the model, or why it cannot be
    fitted to these data."""
    n = state.model.dof
    c = data.conditions
    if name == "harmonics":
        lo, hi = data.q.min(axis=0), data.q.max(axis=0)
        found = cyclic_orders(state, data)
        names = {
            j: HARMONICS + tuple(r for k in found.get(j, ()) for r in cyclic(k))
            for j in range(1, n + 1)
        }
        return _centred(
            tuple(
                Term(
                    "harmonics",
                    j,
                    names[j],
                    (0.0,) * len(names[j]),
                    bounds=(float(lo[j - 1]), float(hi[j - 1])),
                )
                for j in range(1, n + 1)
            ),
            state,
            data,
        )
    if name == "gravity":
        return _centred(
            tuple(
                Term("gravity", j, regs, (0.0,) * len(regs))
                for j in range(1, n + 1)
                for regs in [gravity_regressors(j, n)]
            ),
            state,
            data,
        )
    if name == "ratio":
        ratios = tuple(Term("ratio", j, RATIO, (0.0,)) for j in range(1, n + 1))
        return _centred(ratios, state, data)
    if name == "drift":
        for column, spread in (("temperature_c", MIN_TEMPERATURE_SPREAD_C), ("time_s", 0.0)):
            x = None if c is None else c.column(column)
            if x is not None and float(np.ptp(x)) > spread:
                first = int(np.argmin(c.time_s)) if c is not None and c.time_s is not None else 0
                reference = float(x[first]) if column == "temperature_c" else 0.0
                return (Term("drift", 0, DRIFT, (0.0,) * 4, variable=column, reference=reference),)
        return (
            "needs a time_s column, or a temperature_c column that changes by more than "
            f"{MIN_TEMPERATURE_SPREAD_C:g} °C, during the measurements"
        )
    # compliance
    payload = None if c is None else c.payload_kg
    if payload is None or len(np.unique(payload)) < 2:
        return (
            "needs measurements at two or more payloads (payload_kg), without which a "
            "stiffness cannot be told from the arm's own mass moments: gravity models "
            "the deflection at this payload"
        )
    model = state.model
    if model.mass_model is None:
        return (
            "needs a mass model: mass_kg and com_mm in every [[joint]] of the model (or a "
            "URDF's inertials)"
        )
    start = 0 if c is None or c.time_s is None else int(np.argmin(c.time_s))
    reference = float(payload[start])
    out = []
    for j in range(1, n + 1):
        joint = model.joints[j - 1]
        coupled = {joint.couple_joint} if joint.couple_joint else set()
        coupled |= {k for k, o in enumerate(model.joints, start=1) if o.couple_joint == j}
        regs = compliance_regressors(j, tuple(sorted(coupled)))
        out.append(Term("compliance", j, regs, (0.0,) * len(regs), reference=reference))
    return tuple(out)


def _centred(terms: tuple[Term, ...], state: State, data: Data) -> tuple[Term, ...]:
    """The terms with each regressor's mean over the poses taken off it."""
    frames = chain_frames(state.model, data.q)
    return tuple(
        replace(t, centre=tuple(float(v) for v in joint_regressors(t, data.q, frames).mean(axis=0)))
        for t in terms
    )


@dataclass(frozen=True)
class _Fitted:
    state: State
    sel: tuple[ParameterSpec, ...]


def _identifiable(
    st: State, specs: tuple[ParameterSpec, ...], data: Data, w: Array
) -> dict[int, list[int]]:
    """Each term's regressors (by index) the poses determine: by exact rank, then, after a
    fit, those whose uncertainty stays within a transmission's plausible error (as
    geometric parameters are judged: :func:`weakly_determined`)."""
    ident = analyse(levenberg.linearise(st, specs, data, w).R, specs)
    chosen = tuple(specs[i] for i in ident.identified)
    if not any(s.kind == "term" for s in chosen):
        return {}
    try:
        fit = levenberg.fit(
            st, chosen, data, w, tol=levenberg.COARSE, limit=levenberg.COARSE_PASSES
        )
    except CellcalError:
        return {}
    sigma0 = math.sqrt(fit.lin.cost / max(w.size - len(chosen), 1))
    geometric = [i for i in ident.identified if specs[i].kind != "term"]
    ident = weakly_determined(fit.lin.R, sigma0, ident, spare=geometric)
    keep: dict[int, list[int]] = {}
    for i in ident.identified:
        if specs[i].kind == "term":
            keep.setdefault(specs[i].group, []).append(specs[i].index)
    return keep


def _fit(base: _Fitted, terms: tuple[Term, ...], data: Data, w: Array) -> _Fitted | str:
    """The geometric selection of ``base`` and ``terms`` fitted together, the terms cut
    to their identifiable regressors; or why they could not be."""
    geometric = tuple(s for s in base.sel if s.kind != "term")
    st = replace(base.state, model=base.state.model.with_terms(terms))
    keep = _identifiable(st, geometric + tuple(term_specs(st.model)), data, w)
    if not keep:
        return "not identifiable from these poses (or hidden by their noise)"
    pruned = tuple(
        replace(
            t,
            regressors=tuple(t.regressors[k] for k in sorted(keep[g])),
            coefficients=(0.0,) * len(keep[g]),
            sigma=(),
            centre=tuple(t.centre[k] for k in sorted(keep[g])) if t.centre else (),
        )
        for g, t in enumerate(terms)
        if g in keep
    )
    st = replace(base.state, model=base.state.model.with_terms(pruned))
    sel = geometric + tuple(term_specs(st.model))
    train = (1.0 - 1.0 / REGIONS) * w.size
    if train < EQUATIONS_PER_PARAMETER * len(sel):
        return (
            f"too few poses for it: {len(data.q)} poses give {w.size} equations for "
            f"{len(sel)} parameters with it (a fold's fit needs {EQUATIONS_PER_PARAMETER} "
            "equations per parameter)"
        )
    try:
        fitted = levenberg.fit(st, sel, data, w).state
    except CellcalError as e:
        return f"its fit failed: {e}"
    worst = _largest_turn(fitted, data)
    if worst is not None:
        return worst
    return _Fitted(fitted, sel)


def _largest_turn(state: State, data: Data) -> str | None:
    """Why the joint terms of ``state`` are implausible, or None: a joint turned by more
    than :data:`TERM_LIMIT_DEG` at a measured pose beyond what an offset of its zero (the
    geometry's part) accounts for — half its peak-to-peak over the poses — or, for a
    harmonic, anywhere in its range."""
    joint_terms = tuple(t for t in state.model.terms if t.is_joint_term)
    if not joint_terms:
        return None
    model = state.model
    frames = chain_frames(model, data.q)
    turn = joint_deltas(joint_terms, data.q, frames, model.mass_model, data.conditions)
    half = np.degrees(np.ptp(turn, axis=0)) / 2.0
    for t in joint_terms:
        if t.name == "harmonics":
            grid = np.linspace(*t.bounds, 721)
            q = np.zeros((len(grid), model.dof))
            q[:, t.joint - 1] = grid
            h = joint_deltas((t,), q, None)[:, t.joint - 1]
            half[t.joint - 1] = max(half[t.joint - 1], math.degrees(float(np.ptp(h))) / 2.0)
    joint = int(np.argmax(half))
    if half[joint] <= TERM_LIMIT_DEG:
        return None
    return (
        f"implausible: it turns joint {joint + 1} by ±{half[joint]:.2f}° over the measured "
        f"poses, beyond any transmission's error or deflection ({TERM_LIMIT_DEG}°)"
    )


def _describe(c: Comparison, folds: Folds, accepted: bool) -> str:
    where = f"{len(folds.train)} regions" if folds.kind == "regions" else "later stretches"
    figures = f"blocked cross-validation over {where}: {c.before_mm:.4g} → {c.after_mm:.4g} mm"
    if accepted:
        return f"{figures} ({-100 * c.gain:+.1f} %, z {c.z:.1f})"
    if c.after_mm >= c.before_mm:
        return f"{figures} (no better)"
    return f"{figures}, a gain within its uncertainty (z {c.z:.1f}, needs {Z_ACCEPT:g})"


def _passes(c: Comparison) -> bool:
    return c.z > Z_ACCEPT and c.gain > GAIN


def choose_terms(
    state: State, sel: tuple[ParameterSpec, ...], data: Data, w: Array, request: TermRequest
) -> tuple[State, tuple[ParameterSpec, ...], TermChoice]:
    """The geometric fit ``state`` over ``sel`` with the terms the request and the data
    accept, its parameters, and each term's verdict."""
    if request.mode == FIXED:
        return _fixed(state, sel, data, w, request.names)
    regions = region_folds(state, data)
    c = data.conditions
    order = None if c is None else (c.time_s if c.time_s is not None else c.temperature_c)
    stretches = None if order is None else stretch_folds(order)

    def folds_for(name: str) -> Folds:
        return stretches if name == "drift" and stretches is not None else regions

    def errors(f: _Fitted, folds: Folds) -> Array:
        return held_out_errors(f.state, f.sel, data, w, folds)

    names = TERM_NAMES if request.mode == "auto" else request.names
    current = _Fitted(state, sel)
    geometric_cv = errors(current, regions)
    verdicts: dict[str, TermVerdict] = {}
    possible: dict[str, tuple[Term, ...]] = {}
    for name in names:
        found = candidates(name, state, data)
        if isinstance(found, str):
            verdicts[name] = TermVerdict(name, False, found)
        else:
            possible[name] = found
    judge = _Judge(data, w, folds_for, errors, verdicts)
    if request.mode == "list":
        current = _listed(current, possible, judge)
    else:
        current = _greedy(current, possible, judge)
    final_cv = errors(current, regions)
    return (
        current.state,
        current.sel,
        TermChoice(
            request.mode,
            tuple(verdicts[n] for n in TERM_NAMES if n in verdicts),
            _rms(geometric_cv),
            _rms(final_cv),
        ),
    )


def _fixed(
    state: State, sel: tuple[ParameterSpec, ...], data: Data, w: Array, names: tuple[str, ...]
) -> tuple[State, tuple[ParameterSpec, ...], TermChoice]:
    """The named terms fitted as they are found in these data, nothing judged."""
    verdicts: list[TermVerdict] = []
    terms: tuple[Term, ...] = ()
    for name in names:
        found = candidates(name, state, data)
        if isinstance(found, str):
            verdicts.append(TermVerdict(name, False, found))
        else:
            terms += found
    fitted = _fit(_Fitted(state, sel), terms, data, w) if terms else _Fitted(state, sel)
    if isinstance(fitted, str):
        verdicts += [TermVerdict(n, False, fitted) for n in names]
        fitted = _Fitted(state, sel)
    present = {t.name for t in fitted.state.model.terms}
    verdicts += [TermVerdict(n, True, "fitted as given") for n in names if n in present]
    return fitted.state, fitted.sel, TermChoice(FIXED, tuple(verdicts), math.nan, math.nan)


def _rms(e: Array) -> float:
    ok = np.isfinite(e)
    return math.sqrt(float(np.mean(e[ok] ** 2))) if ok.any() else math.nan


@dataclass(frozen=True)
class _Judge:
    """What judging terms needs: the data and weights, the folds of a term (regions, or
    stretches for a drift), a fit's held-out errors on folds, and the verdicts so far."""

    data: Data
    w: Array
    folds_for: Callable[[str], Folds]
    errors: Callable[[_Fitted, Folds], Array]
    verdicts: dict[str, TermVerdict]


def _listed(current: _Fitted, possible: dict[str, tuple[Term, ...]], judge: _Judge) -> _Fitted:
    """Fit every listed term; judge each by the listed set without it."""
    data, w, verdicts = judge.data, judge.w, judge.verdicts
    folds_for, errors = judge.folds_for, judge.errors
    every = tuple(t for cand in possible.values() for t in cand)
    if not every:
        return current
    fitted = _fit(current, every, data, w)
    if isinstance(fitted, str):
        for name in possible:
            verdicts[name] = TermVerdict(name, False, fitted)
        return current
    present = {t.name for t in fitted.state.model.terms}
    for name in possible:
        if name not in present:
            verdicts[name] = TermVerdict(name, False, "not identifiable from these poses")
            continue
        others = tuple(t for n, cand in possible.items() if n != name for t in cand)
        without = _fit(current, others, data, w) if others else current
        folds = folds_for(name)
        if isinstance(without, str):
            verdicts[name] = TermVerdict(name, True, "fitted as listed")
            continue
        cmp = compare(errors(without, folds), errors(fitted, folds))
        ok = _passes(cmp)
        note = "" if ok else " — fitted as listed, though the gate would not accept it"
        verdicts[name] = TermVerdict(name, True, _describe(cmp, folds, ok) + note, cmp)
    return fitted


def _greedy(current: _Fitted, possible: dict[str, tuple[Term, ...]], judge: _Judge) -> _Fitted:
    """Add, one at a time, the term that lowers the blocked error most, while one does."""
    data, w, verdicts = judge.data, judge.w, judge.verdicts
    folds_for, errors = judge.folds_for, judge.errors
    terms: tuple[Term, ...] = ()
    last: dict[str, tuple[Comparison, Folds]] = {}
    while possible:
        best: tuple[float, str, _Fitted, Comparison] | None = None
        for name, cand in possible.items():
            fitted = _fit(current, terms + cand, data, w)
            if isinstance(fitted, str):
                verdicts[name] = TermVerdict(name, False, fitted)
                continue
            folds = folds_for(name)
            cmp = compare(errors(current, folds), errors(fitted, folds))
            last[name] = (cmp, folds)
            if _passes(cmp) and (best is None or cmp.after_mm < best[0]):
                best = (cmp.after_mm, name, fitted, cmp)
        for name in [n for n in possible if n in verdicts]:
            del possible[name]
        if best is None:
            break
        _, name, current, cmp = best
        terms = current.state.model.terms
        verdicts[name] = TermVerdict(name, True, _describe(cmp, folds_for(name), True), cmp)
        del possible[name]
    for name, (cmp, folds) in last.items():
        if name not in verdicts:
            verdicts[name] = TermVerdict(name, False, _describe(cmp, folds, False), cmp)
    return current
