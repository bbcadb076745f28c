"""(Size: about 440 lines — calibrate() is one pipeline (start, baseline, identifiability,
the fits, the parameter choice, the error terms, the result); the fit itself is in
levenberg.py, the choices in parameter_choice.py and term_choice.py, the data in
observations.py, the result's estimates in estimates.py.)

Identification of kinematic errors from target positions measured by a sensor.

``calibrate(nominal, q, measured)`` estimates, together, the identifiable kinematic
corrections, the target offset on the flange and the sensor frame — the last two
are unknown at the start. It starts from a closed-form registration of the nominal
model's positions to the measurements (SVD, then a linear solve for the target offset),
fits the sensor frame and target offset alone (the "before" model: nominal
geometry, best-fit frames), chooses the identifiable parameters from the Jacobian at
that point, and runs Levenberg–Marquardt (cellcal.calib.levenberg) on them.
Standard uncertainties come from the a-posteriori covariance σ₀²(JᵀJ)⁻¹. Several
targets (one offset each), several sessions (one sensor frame each) and measured
orientations are carried by ``cellcal.calib.observations.Data``.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence

import numpy as np

from cellcal.calib import levenberg
from cellcal.calib.acceptance import (
    ACCURACY_CLASS_MM,
    Finding,
    assess,
    check_data,
    diagnose,
)
from cellcal.calib.calibration_result import CalibrationResult, ParameterEstimate, rms
from cellcal.calib.error_model import (
    KINEMATIC_KINDS,
    Groups,
    ParameterSpec,
    State,
    parameter_specs,
    predict,
)
from cellcal.calib.error_terms import Conditions
from cellcal.calib.estimates import (
    current_name,
    estimates,
    estimates_preview,
    expand_fix,
    frame_std,
    with_term_sigma,
)
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import analyse, condition_number, weakly_determined
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.observations import (
    STILL_MM,
    Data,
    balance,
    check_measurements,
    check_orientations,
    check_sessions,
    initial_state,
    register_sessions,
    weights,
)
from cellcal.calib.parameter_choice import FOLDS, Choice, choose
from cellcal.calib.pose_warnings import on_a_surface, pose_warnings
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.robust_fit import ROBUST_LOSSES, robust_fit
from cellcal.calib.term_choice import TermChoice, TermRequest, choose_terms, parse_terms
from cellcal.errors import (
    AcceptanceError,
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MirroredCorrespondenceError,
)

__all__ = [
    "ROBUST_LOSSES",
    "CalibrationResult",
    "Groups",
    "ParameterEstimate",
    "calibrate",
    "fit_frames",
    "on_a_surface",
]

#: Above this condition number of the (unit-scaled) identification Jacobian a warning
#: says the poses are poorly chosen; well-spread poses with varied wrist orientation
#: give tens to a few hundred, the paper's fixed-orientation cube about 5e3.
ILL_CONDITIONED = 1e3


# --------------------------------------------------------------------------- the fit


def _frame_target_specs(specs: tuple[ParameterSpec, ...]) -> tuple[ParameterSpec, ...]:
    return tuple(s for s in specs if s.kind not in KINEMATIC_KINDS and s.kind != "term")


@levenberg.one_blas_thread
def fit_frames(
    model: RobotModel,
    q: Array,
    measured: Array,
    sigma: Array | None = None,
    groups: Groups | None = None,
    conditions: Conditions | None = None,
) -> State:
    """The nominal geometry with best-fit sensor frames and target offsets (the
    "before" model of a calibration, and the baseline of validation); a model's error
    terms at the measurements' ``conditions``."""
    q, measured, sigma = check_measurements(model, q, measured, sigma)
    g = groups if groups is not None else Groups.single(len(q))
    data = Data(q, measured, g, None, conditions)
    return _fit_frames(model, data, weights(sigma, len(q)))


def _fit_frames(model: RobotModel, data: Data, w: Array) -> State:
    state = initial_state(model, data.q, data.measured, data.groups, data.orientations)
    specs = _frame_target_specs(
        parameter_specs(model, groups=data.groups, orientation=data.orientations is not None)
    )
    lin = levenberg.linearise(state, specs, data, w)
    ident = analyse(lin.R, specs)
    sel = tuple(specs[i] for i in ident.identified)
    lost = {s.group for s in specs if s.kind == "target_offset" and s not in sel}
    at: levenberg.Linearisation | None = lin.subset(list(ident.identified))
    if lost:
        # The poses do not determine a whole target offset: keep its nominal value (the
        # closed-form start may have given it any value) and register again.
        target_offsets = state.target_offsets.copy()
        target_offsets[sorted(lost)] = model.target_offset
        k = target_kinematics(model, data.q, target_offsets[data.groups.target], jacobian=False)
        Rs, ts = register_sessions(k.p, data.measured, data.groups)
        state = State(model, target_offsets, Rs, ts, state.pivots, state.target_rotations)
        at = None
    return levenberg.fit(state, sel, data, w, at).state


def _nominal_offsets(
    state: State, specs: tuple[ParameterSpec, ...], sel: tuple[ParameterSpec, ...], data: Data
) -> State:
    """``state`` with each target-offset component the fit leaves out (pinned by --fix,
    or not determined by the poses) at its nominal value, and the sensor frames
    registered again to it: the best-fit baseline estimates every offset, and a fit that
    starts there and does not free it would keep that estimate, not the nominal value it
    reports."""
    model = state.model
    target_offsets = state.target_offsets.copy()
    for s in specs:
        if s.kind == "target_offset" and s not in sel:
            target_offsets[s.group, s.axis] = model.target_offset[s.axis]
    if np.array_equal(target_offsets, state.target_offsets):
        return state
    k = target_kinematics(model, data.q, target_offsets[data.groups.target], jacobian=False)
    Rs, ts = register_sessions(k.p, data.measured, data.groups)
    return State(model, target_offsets, Rs, ts, state.pivots, state.target_rotations)


@levenberg.one_blas_thread
def frames_rms(model: RobotModel, q: Array, measured: Array, groups: Groups | None = None) -> float:
    """RMS position residual (mm) of the model with best-fit frames; joint limits not
    checked (for trying reinterpretations of data that do not fit)."""
    data = Data(q, measured, groups if groups is not None else Groups.single(len(q)))
    st = _fit_frames(model, data, np.ones((len(q), 3)))
    return rms(measured - predict(st, q, data.groups))


def _refuse_or_note(
    findings: list[Finding], accept: bool, notes: list[str], accepted: list[str]
) -> None:
    if not findings:
        return
    if not accept:
        raise findings[0].refusal()
    notes += [f"accepted despite the check '{f.check}': {f.message}" for f in findings]
    accepted += [f.check for f in findings]


def _sigma0(residuals: Array, w: Array, dof: int) -> float:
    return float(np.sqrt(np.sum((residuals * w) ** 2) / max(dof, 1)))


@levenberg.one_blas_thread
def calibrate(
    nominal: RobotModel,
    q: Array,
    measured: Array,
    sigma: Array | None = None,
    *,
    robust: str | None = None,
    paper_parameters: bool = False,
    fix: Collection[str] = (),
    accept: bool = False,
    alternatives: Sequence[RobotModel] = (),
    groups: Groups | None = None,
    orientations: Array | None = None,
    terms: TermRequest | str = "geometric",
    conditions: Conditions | None = None,
) -> CalibrationResult:
    """Identify kinematic errors, target offsets and sensor frames together.

    ``q``: joint readings (N×n, rad); ``measured``: target positions in the sensor
    frame (N×3, mm); ``sigma``: their 1σ per axis (N×3, mm) to weight the fit;
    ``robust``: a robust loss (huber, soft_l1, cauchy) after the least-squares fit;
    ``paper_parameters``: the paper's θ, d, a, α on every row (no β); ``fix``: parameter
    names (or ``kinematics``, ``target_offset``) pinned at nominal; ``groups``: the target and the
    session (sensor set-up) of each row, each with its own offset or frame;
    ``orientations``: measured target orientations (N×3×3) of a 6-DOF sensor. A
    result that fails an acceptance check raises :class:`AcceptanceError` unless
    ``accept`` (then the failures are among the warnings); ``alternatives``: other models
    to try when diagnosing data that do not fit; ``terms``: error terms beyond geometry
    (``auto``, ``geometric`` or a comma list, :mod:`cellcal.calib.term_choice`), read
    with the measurements' ``conditions`` (time, temperature, payload).
    """
    request = parse_terms(terms) if isinstance(terms, str) else terms
    if nominal.terms:
        # a calibrated model as the start: --fix kinematics keeps its terms as they are;
        # otherwise they are chosen afresh with the geometry
        if "kinematics" in {current_name(f) for f in fix}:
            request = TermRequest("geometric")
        else:
            nominal = nominal.geometry
    q, measured, sigma = check_measurements(nominal, q, measured, sigma)
    orientations = check_orientations(orientations, len(q))
    if robust is not None and robust not in ROBUST_LOSSES:
        raise InputError(
            f"unknown robust loss {robust!r}; choose one of {', '.join(ROBUST_LOSSES)}"
        )
    N = len(q)
    if N < 3:
        raise DegenerateGeometryError(f"need at least 3 measurements, got {N}")
    g = groups if groups is not None else Groups.single(N)
    if len(g.target) != N or len(g.session) != N:
        raise InputError(f"groups: expected {N} target and session labels")
    data = Data(q, measured, g, orientations, conditions)
    six = orientations is not None
    w = weights(sigma, N, six)
    warnings: list[str] = []
    accepted: list[str] = []
    specs = parameter_specs(nominal, paper_parameters=paper_parameters, groups=g, orientation=six)
    pinned = expand_fix(specs, fix)
    findings: list[Finding] = []
    still = False  # a session whose target did not move at all
    for s in range(len(g.sessions)):
        rows = g.session == s
        findings += check_data(nominal, q[rows], measured[rows], nominal.target_offset)
        still |= bool(np.ptp(measured[rows], axis=0).max() <= STILL_MM)
    if not still:  # points on a line are degenerate geometry (exit 2) ...
        check_sessions(measured, g)
    # ... a target that stays put while the robot moves does not follow it (exit 3)
    _refuse_or_note(findings[:1], accept, warnings, accepted)
    check_sessions(measured, g)

    def frames_fit(model: RobotModel, qq: Array, mm: Array) -> float:
        return frames_rms(model, qq, mm, g)

    def diagnosis(what: str) -> AcceptanceError:
        return diagnose(nominal, q, measured, frames_fit, alternatives, what=what).refusal()

    try:
        baseline = _fit_frames(nominal, data, w)
    except ConvergenceError:
        raise diagnosis("the registration of the nominal model did not converge") from None
    except MirroredCorrespondenceError:
        raise diagnosis(
            "the nominal model's positions match the measurements only mirrored"
        ) from None
    residuals_before = measured - predict(baseline, q, g)
    if rms(residuals_before) > ACCURACY_CLASS_MM:
        finding = diagnose(
            nominal,
            q,
            measured,
            frames_fit,
            alternatives,
            what=f"the nominal model with best-fit frames leaves RMS "
            f"{rms(residuals_before):.3g} mm, far worse than any robot's accuracy class",
        )
        _refuse_or_note([finding], accept, warnings, accepted)

    base = levenberg.linearise(baseline, specs, data, w)
    ident = analyse(base.R, specs, fixed=pinned)
    sel = tuple(specs[i] for i in ident.identified)
    equations = w.size
    if len(sel) >= equations:
        raise InputError(
            f"{N} measurements give {equations} equations for {len(sel)} identifiable "
            f"parameters; measure at least {len(sel) // 3 + 1} poses"
        )
    # Identifiability as a matter of degree: fit, estimate the noise, leave at nominal
    # what the noise hides, and fit again from the baseline without it.
    # The first fit only has to estimate σ₀ and the Jacobian at the solution: it stops
    # once no estimate would move by a tenth of its uncertainty, or after a few passes.
    start = _nominal_offsets(baseline, specs, sel, data)
    first: levenberg.Fit | None = None
    nfev = 0
    try:
        at = base.subset(list(ident.identified)) if start is baseline else None
        first = levenberg.fit(
            start, sel, data, w, at, tol=levenberg.COARSE, limit=levenberg.COARSE_PASSES
        )
        nfev = first.passes
        for _ in range(2 if six else 0):
            w = balance(w, data.residuals(first.state))
            first = levenberg.fit(
                start, sel, data, w, tol=levenberg.COARSE, limit=levenberg.COARSE_PASSES
            )
            nfev += first.passes
        at_point = first.lin
    except ConvergenceError:
        at_point = levenberg.linearise(baseline, sel, data, w)
    sigma0_first = math.sqrt(at_point.cost / max(equations - len(sel), 1))
    ident = weakly_determined(at_point.R, sigma0_first, ident)
    sel = tuple(specs[i] for i in ident.identified)
    try:
        if first is not None and not ident.weak:  # the same set: go on to convergence
            final = levenberg.fit(first.state, sel, data, w, first.lin)
        else:
            final = levenberg.fit(_nominal_offsets(baseline, specs, sel, data), sel, data, w)
    except ConvergenceError:
        raise diagnosis("the identification did not converge") from None
    nfev += final.passes
    choice: Choice | None = None
    if ident.weak and first is not None and robust is None:

        def plausible(st: State, chosen: tuple[ParameterSpec, ...]) -> bool:
            far = st.target_offsets[int(np.argmax(np.linalg.norm(st.target_offsets, axis=1)))]
            return not assess(nominal, estimates_preview(st, nominal, chosen), far)

        if plausible(final.state, sel):
            choice = choose(ident, at_point.R, sigma0_first, final.state, data, w, plausible)
            if choice.freed:
                ident = choice.ident
                sel = tuple(specs[i] for i in ident.identified)
                final = levenberg.fit(final.state, sel, data, w)
                nfev += final.passes
            if choice.tempting:
                names = ", ".join(n for n, _ in choice.tempting)
                best = min(cv for _, cv in choice.tempting)
                warnings.append(
                    f"freeing {names} would lower the {FOLDS}-fold held-out error from "
                    f"{choice.chosen_mm:.4g} to as little as {best:.4g} (mm, weighted) but puts "
                    "a correction beyond manufacturing tolerance: left at nominal (an "
                    "unmodelled error, or the wrong model?)"
                )
    term_choice: TermChoice | None = None
    if request.mode != "geometric":
        state_t, sel, term_choice = choose_terms(final.state, sel, data, w, request)
        if state_t is not final.state:
            final = levenberg.fit(state_t, sel, data, w)
            nfev += final.passes
    P = len(sel)
    if robust is not None:
        r = np.linalg.norm(data.residuals(final.state) * w, axis=1)
        f_scale = 2.5 * max(float(np.median(r)) / 1.5382, 1e-12)
        try:
            final = robust_fit(final.state, sel, data, w, robust, f_scale)
        except ConvergenceError:
            raise diagnosis(f"the robust ({robust}) identification did not converge") from None
        nfev += final.passes
    state = final.state
    warnings += pose_warnings(ident, specs, sel)
    flat = on_a_surface(
        target_kinematics(nominal, q, baseline.target_offsets[g.target], jacobian=False).p
    )
    if flat is not None:
        warnings.append(flat)
    farthest = state.target_offsets[int(np.argmax(np.linalg.norm(state.target_offsets, axis=1)))]
    _refuse_or_note(
        assess(nominal, estimates_preview(state, nominal, sel), farthest),
        accept,
        warnings,
        accepted,
    )
    if ident.condition_number > ILL_CONDITIONED:
        warnings.append(
            f"the identification is ill-conditioned (condition number "
            f"{ident.condition_number:.3g}): vary the wrist orientation between poses and "
            "spread them over a larger volume"
        )

    # the same poses' condition number with every coordinate weighted alike, as the plan
    # computes it before anything is measured (positions only)
    equal = base.R
    if sigma is not None or six:
        ones = np.ones((N, 3))
        equal = levenberg.linearise(baseline, specs, Data(q, measured, g), ones).R
    cond_equal = condition_number(equal, ident.identified)
    full = data.residuals(state)
    residuals = full[:, :3]
    dof = equations - P
    sigma0 = _sigma0(full, w, dof)
    try:
        cov: Array = np.asarray(sigma0**2 * np.linalg.inv(final.lin.G), dtype=np.float64)
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        cov = np.full((P, P), np.nan)
        std = np.full(P, np.nan)
        warnings.append("the normal matrix is singular at the solution: no uncertainties")

    state = with_term_sigma(state, sel, std)
    estimated = estimates(state, nominal, specs, sel, std, ident)
    target_offset_std = np.array([e.std for e in estimated if e.kind == "target_offset"]).reshape(
        -1, 3
    )
    frames_std = np.stack([frame_std(state, sel, cov, s) for s in range(len(g.sessions))])
    return CalibrationResult(
        nominal=nominal,
        calibrated=state.model,
        target_offset=state.target_offset,
        target_offset_std=target_offset_std[0],
        T_sensor_base=state.T_sensor_base,
        frame_std=frames_std[0],
        parameters=estimated,
        identifiability=ident,
        n_points=N,
        dof=dof,
        sigma0=sigma0,
        residuals=residuals,
        residuals_before=residuals_before,
        evaluations=nfev,
        weighted=sigma is not None,
        robust=robust,
        warnings=tuple(warnings),
        accepted_despite=tuple(accepted),
        groups=g,
        target_offsets=state.target_offsets,
        target_offsets_std=target_offset_std,
        frames=np.stack([state.frame(s) for s in range(len(g.sessions))]),
        frames_std=frames_std,
        target_rotations=state.target_rotations,
        orientation_residuals=None if not six else full[:, 3:],
        covariance=cov,
        covariance_specs=sel,
        pivots=state.pivots,
        condition_number_equal_weights=cond_equal,
        parameter_choice=choice,
        term_choice=term_choice,
    )
