"""(Size: about 550 lines — calibrate() is one pipeline (start, baseline, identifiability,
the fits, the parameter choice, the result); the fit itself is in levenberg.py, the
choice in parameter_choice.py, the data in observations.py.)

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
from scipy.optimize import least_squares

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
    apply,
    parameter_specs,
    predict,
)
from cellcal.calib.geometry import Array, skew, so3_log, wrap_deg
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
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import (
    AcceptanceError,
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MirroredCorrespondenceError,
)

__all__ = ["CalibrationResult", "Groups", "ParameterEstimate", "calibrate", "fit_frames"]

ROBUST_LOSSES = ("huber", "soft_l1", "cauchy")
#: Above this condition number of the (unit-scaled) identification Jacobian a warning
#: says the poses are poorly chosen; well-spread poses with varied wrist orientation
#: give tens to a few hundred, the paper's fixed-orientation cube about 5e3.
ILL_CONDITIONED = 1e3


# --------------------------------------------------------------------------- input checks


# --------------------------------------------------------------------------- the fit


def _robust_fit(
    state: State,
    specs: tuple[ParameterSpec, ...],
    data: Data,
    w: Array,
    robust: str,
    f_scale: float,
) -> levenberg.Fit:
    """TRF with a robust loss over ``specs`` from ``state`` (scipy: the loss's
    reweighting is what it is made for)."""

    def fun(x: Array) -> Array:
        out: Array = (data.residuals(apply(state, specs, x)) * w).ravel()
        return out

    def jac(x: Array) -> Array:
        J = data.jacobian(apply(state, specs, x), specs)
        out: Array = -(J * w[:, :, None]).reshape(-1, len(specs))
        return out

    res = least_squares(
        fun,
        np.zeros(len(specs)),
        jac=jac,
        method="trf",
        loss=robust,
        f_scale=f_scale,
        x_scale="jac",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    if not res.success or not np.all(np.isfinite(res.x)):
        raise ConvergenceError(f"identification did not converge: {res.message}")
    J = np.asarray(res.jac)
    lin = levenberg.Linearisation(J.T @ J, np.zeros(len(specs)), float(2.0 * res.cost))
    return levenberg.Fit(apply(state, specs, res.x), lin, int(res.nfev))


def _frame_target_specs(specs: tuple[ParameterSpec, ...]) -> tuple[ParameterSpec, ...]:
    return tuple(s for s in specs if s.kind not in KINEMATIC_KINDS)


@levenberg.one_blas_thread
def fit_frames(
    model: RobotModel,
    q: Array,
    measured: Array,
    sigma: Array | None = None,
    groups: Groups | None = None,
) -> State:
    """The nominal geometry with best-fit sensor frames and target offsets (the
    "before" model of a calibration, and the baseline of validation)."""
    q, measured, sigma = check_measurements(model, q, measured, sigma)
    data = Data(q, measured, groups if groups is not None else Groups.single(len(q)))
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


#: Earlier spellings ``--fix`` still takes: the group ``tool`` and the names ``tool_x`` …
#: ``tool_rz`` (``:A`` for a target's group kept), now ``target_offset``, ``target_offset_x``,
#: ``target_rotation_x``.
_OLD_PREFIXES = (("tool_r", "target_rotation_"), ("tool_", "target_offset_"))


def _current_name(item: str) -> str:
    if item == "tool":
        return "target_offset"
    for old, new in _OLD_PREFIXES:
        if item.startswith(old) and item[len(old) : len(old) + 1] in ("x", "y", "z"):
            return new + item[len(old) :]
    return item


def _expand_fix(specs: tuple[ParameterSpec, ...], fix: Collection[str]) -> frozenset[str]:
    """Parameter names to pin: names, or the groups ``kinematics``, ``target_offset``
    (earlier spellings read: :data:`_OLD_PREFIXES`)."""
    names = {s.name for s in specs}
    out: set[str] = set()
    for item in map(_current_name, fix):
        if item == "kinematics":
            out |= {s.name for s in specs if s.kind in KINEMATIC_KINDS}
        elif item == "target_offset":
            out |= {s.name for s in specs if s.kind in ("target_offset", "target_rotation")}
        elif item in names:
            out.add(item)
        else:
            raise InputError(
                f"--fix {item}: no such parameter; choose from kinematics, target_offset, or "
                f"{', '.join(s.name for s in specs if not s.kind.startswith('frame'))}"
            )
    return frozenset(out)


def _refuse_or_note(
    findings: list[Finding], accept: bool, notes: list[str], accepted: list[str]
) -> None:
    if not findings:
        return
    if not accept:
        raise findings[0].refusal()
    notes += [f"accepted despite the check '{f.check}': {f.message}" for f in findings]
    accepted += [f.check for f in findings]


#: Targets whose spread off their best-fit plane is below this fraction of their spread
#: along it lie on a surface.
SURFACE_RATIO = 0.05


def on_a_surface(points: Array) -> str | None:
    """A warning when the targets (N×3, one frame) lie near one plane, else None: a model
    fitted to a surface may predict worse than nominal away from it (a real UR5's
    surface session: 3.0 mm held-out against the nominal model's 1.3 mm)."""
    if len(points) < 4:
        return None
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False) / math.sqrt(len(points))
    if not s[2] < SURFACE_RATIO * s[0]:
        return None
    return (
        f"the targets lie near one surface ({s[2]:.2g} mm RMS off a plane, "
        f"{s[0]:.0f} × {s[1]:.0f} mm RMS along it): the model is fitted to that surface and "
        "may predict worse than nominal away from it — validate off it (--validate) or "
        "spread the poses over a volume"
    )


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
    to try when diagnosing data that do not fit.
    """
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
    data = Data(q, measured, g, orientations)
    six = orientations is not None
    w = weights(sigma, N, six)
    warnings: list[str] = []
    accepted: list[str] = []
    specs = parameter_specs(nominal, paper_parameters=paper_parameters, groups=g, orientation=six)
    pinned = _expand_fix(specs, fix)
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
    P = len(sel)
    if robust is not None:
        r = np.linalg.norm(data.residuals(final.state) * w, axis=1)
        f_scale = 2.5 * max(float(np.median(r)) / 1.5382, 1e-12)
        try:
            final = _robust_fit(final.state, sel, data, w, robust, f_scale)
        except ConvergenceError:
            raise diagnosis(f"the robust ({robust}) identification did not converge") from None
        nfev += final.passes
    state = final.state
    lost = [i for i, s in enumerate(specs) if s.kind == "target_offset" and s not in sel]
    rank = [specs[i].name for i in lost if ident.reason(i) == "rank"]
    hidden = [specs[i].name for i in lost if ident.reason(i) == "weak"]
    if rank:
        warnings.append(
            f"the target offset ({', '.join(rank)}) is not identifiable from these poses "
            "(does the flange orientation never change?); it stays at its nominal value and "
            "the model holds only at the measured orientations"
        )
    if hidden:
        warnings.append(
            f"the target offset ({', '.join(hidden)}) is hidden by the noise at these poses "
            "(its uncertainty exceeds 1 mm: the flange orientation varies too little); it "
            "stays at its nominal value — vary the wrist orientation more"
        )
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

    sel_index = {s.name: k for k, s in enumerate(sel)}
    estimates = []
    for i, sp in enumerate(specs):
        if sp.kind.startswith("frame"):
            continue
        k = sel_index.get(sp.name)
        if sp.kind == "target_offset":
            value = float(state.target_offsets[sp.group, sp.axis])
        elif sp.kind == "target_rotation":
            assert state.target_rotations is not None
            value = math.degrees(float(so3_log(state.target_rotations[sp.group])[sp.axis]))
        else:
            value = sp.to_display(
                getattr(state.model.joints[sp.joint - 1], sp.kind)
                - getattr(nominal.joints[sp.joint - 1], sp.kind)
            )
            value = wrap_deg(value) if sp.is_angle else value
        sd = 0.0 if k is None else sp.to_display(float(std[k]))
        estimates.append(
            ParameterEstimate(
                sp.name,
                sp.kind,
                sp.joint,
                sp.unit,
                k is not None,
                value,
                sd,
                "" if k is not None else ident.reason(i),
            )
        )
    target_offset_std = np.array([e.std for e in estimates if e.kind == "target_offset"]).reshape(
        -1, 3
    )
    frame_std = np.stack([_frame_std(state, sel, cov, s) for s in range(len(g.sessions))])
    return CalibrationResult(
        nominal=nominal,
        calibrated=state.model,
        target_offset=state.target_offset,
        target_offset_std=target_offset_std[0],
        T_sensor_base=state.T_sensor_base,
        frame_std=frame_std[0],
        parameters=tuple(estimates),
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
        frames_std=frame_std,
        target_rotations=state.target_rotations,
        orientation_residuals=None if not six else full[:, 3:],
        covariance=cov,
        covariance_specs=sel,
        pivots=state.pivots,
        condition_number_equal_weights=cond_equal,
        parameter_choice=choice,
    )


def _frame_std(state: State, sel: tuple[ParameterSpec, ...], cov: Array, session: int = 0) -> Array:
    """Standard uncertainty of a session's T_sensor_base rotation vector and
    translation (at the sensor origin), from the covariance of the pivot
    parameterisation."""
    idx = [k for k, s in enumerate(sel) if s.kind.startswith("frame") and s.group == session]
    if len(idx) != 6:
        return np.full(6, np.nan)
    C = cov[np.ix_(idx, idx)]
    # t = E(ω)(t₀ − pivot) + pivot + δt  ⇒  ∂t/∂ω = −[t₀ − pivot]×, ∂t/∂δt = I.
    G = np.eye(6)
    G[3:6, 0:3] = -skew(state.ts[session] - state.pivots[session])
    out: Array = np.sqrt(np.clip(np.diag(G @ C @ G.T), 0.0, None))
    return out


def estimates_preview(
    state: State, nominal: RobotModel, sel: tuple[ParameterSpec, ...]
) -> list[tuple[str, str, float]]:
    """(name, unit, correction) of the identified kinematic parameters, display units."""
    out = []
    for sp in sel:
        if sp.kind in KINEMATIC_KINDS:
            j = sp.joint - 1
            delta = getattr(state.model.joints[j], sp.kind) - getattr(nominal.joints[j], sp.kind)
            out.append((sp.name, sp.unit, sp.to_display(delta)))
    return out
