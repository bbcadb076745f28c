"""Identification of kinematic errors from target positions measured by an instrument.

``calibrate(nominal, q, measured)`` estimates, together, the identifiable kinematic
corrections, the target offset on the flange and the instrument frame — the last two
are unknown at the start. It starts from a closed-form registration of the nominal
model's positions to the measurements (SVD, then a linear solve for the target offset),
fits the instrument frame and target offset alone (the "before" model: nominal
geometry, best-fit frames), chooses the identifiable parameters from the Jacobian at
that point, and runs Levenberg–Marquardt (scipy.optimize.least_squares) on them.
Standard uncertainties come from the a-posteriori covariance σ₀²(JᵀJ)⁻¹.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence

import numpy as np
from scipy.optimize import least_squares

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
    ParameterSpec,
    State,
    apply,
    jacobian,
    parameter_specs,
    predict,
)
from cellcal.calib.geometry import Array, skew, wrap_deg
from cellcal.calib.identifiability import analyse, weakly_determined
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.registration import fit_rigid
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import (
    AcceptanceError,
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MirroredCorrespondenceError,
)

__all__ = ["CalibrationResult", "ParameterEstimate", "calibrate", "fit_frames"]

ROBUST_LOSSES = ("huber", "soft_l1", "cauchy")
#: Above this condition number of the (unit-scaled) identification Jacobian a warning
#: says the poses are poorly chosen; well-spread poses with varied wrist orientation
#: give tens to a few hundred, the paper's fixed-orientation cube about 5e3.
ILL_CONDITIONED = 1e3


# --------------------------------------------------------------------------- input checks


def check_measurements(
    model: RobotModel, q: Array, measured: Array, sigma: Array | None
) -> tuple[Array, Array, Array | None]:
    """Shapes, finiteness and joint limits; returns float64 copies."""
    q = np.asarray(q, dtype=np.float64)
    m = np.asarray(measured, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != model.dof:
        raise InputError(f"joint readings: expected N×{model.dof}, got shape {q.shape}")
    if m.shape != (len(q), 3):
        raise InputError(f"measurements: expected {len(q)}×3 positions, got shape {m.shape}")
    for name, arr in (("joint readings", q), ("measurements", m)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if len(bad):
            raise InputError(f"{name}: row {int(bad[0]) + 1} is not finite")
    lo, hi = model.limits
    outside = (q < lo - 1e-9) | (q > hi + 1e-9)
    if outside.any():
        r, j = (int(v) for v in np.argwhere(outside)[0])
        raise InputError(
            f"row {r + 1}: joint {j + 1} reads {math.degrees(q[r, j]):.3f}°, outside the "
            f"model's limits [{math.degrees(lo[j]):.1f}°, {math.degrees(hi[j]):.1f}°]"
        )
    s = None
    if sigma is not None:
        s = np.asarray(sigma, dtype=np.float64)
        if s.shape != m.shape or not np.isfinite(s).all() or (s <= 0).any():
            raise InputError("sx, sy, sz: must be positive, finite, one triple per row")
    return q, m, s


# --------------------------------------------------------------------------- the fit


def initial_state(model: RobotModel, q: Array, measured: Array) -> State:
    """Closed-form start: register the nominal positions to the measurements (SVD), then
    solve the target offset and the translation linearly, and register once more."""
    k = target_kinematics(model, q, model.tool, jacobian=False)
    fit = fit_rigid(k.p, measured)
    R = fit.R
    # measured − R·o_flange = R·R_flange·tool + t: linear in (tool, t).
    A = np.concatenate(
        [np.einsum("ij,njk->nik", R, k.R_flange), np.broadcast_to(np.eye(3), (len(q), 3, 3))],
        axis=2,
    )
    b = measured - (k.p - k.R_flange @ model.tool) @ R.T
    sol, _, rank, _ = np.linalg.lstsq(A.reshape(-1, 6), b.reshape(-1), rcond=1e-9)
    tool = sol[:3] if rank == 6 else model.tool.copy()
    k = target_kinematics(model, q, tool, jacobian=False)
    fit = fit_rigid(k.p, measured)
    return State(model, tool, fit.R, fit.t, measured.mean(axis=0))


def _weights(sigma: Array | None, n: int) -> Array:
    return np.ones((n, 3)) if sigma is None else 1.0 / sigma


def _least_squares(
    state: State,
    specs: tuple[ParameterSpec, ...],
    q: Array,
    measured: Array,
    w: Array,
    robust: str | None = None,
    f_scale: float = 1.0,
) -> tuple[State, Array, int]:
    """Levenberg–Marquardt (or TRF with a robust loss) over ``specs`` from ``state``."""

    def fun(x: Array) -> Array:
        out: Array = ((measured - predict(apply(state, specs, x), q)) * w).ravel()
        return out

    def jac(x: Array) -> Array:
        _, J = jacobian(apply(state, specs, x), q, specs)
        out: Array = -(J * w[:, :, None]).reshape(-1, len(specs))
        return out

    x0 = np.zeros(len(specs))
    kwargs: dict[str, object] = {"xtol": 1e-12, "ftol": 1e-12, "gtol": 1e-12}
    if robust is None:
        res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", **kwargs)
    else:
        res = least_squares(
            fun, x0, jac=jac, method="trf", loss=robust, f_scale=f_scale, x_scale="jac", **kwargs
        )
    if not res.success or not np.all(np.isfinite(res.x)):
        raise ConvergenceError(f"identification did not converge: {res.message}")
    st = apply(state, specs, res.x)
    return st, np.asarray(res.jac), int(res.nfev)


def _frame_tool_specs(specs: tuple[ParameterSpec, ...]) -> tuple[ParameterSpec, ...]:
    return tuple(s for s in specs if s.kind not in KINEMATIC_KINDS)


def fit_frames(model: RobotModel, q: Array, measured: Array, sigma: Array | None = None) -> State:
    """The nominal geometry with best-fit instrument frame and target offset (the
    "before" model of a calibration, and the baseline of validation)."""
    q, measured, sigma = check_measurements(model, q, measured, sigma)
    return _fit_frames(model, q, measured, _weights(sigma, len(q)))


def _fit_frames(model: RobotModel, q: Array, measured: Array, w: Array) -> State:
    state = initial_state(model, q, measured)
    specs = _frame_tool_specs(parameter_specs(model))
    _, J = jacobian(state, q, specs)
    ident = analyse((J * w[:, :, None]).reshape(-1, len(specs)), specs)
    sel = tuple(specs[i] for i in ident.identified)
    if any(s.kind == "tool" for s in specs if s not in sel):
        # The poses do not determine the whole target offset: keep its nominal value
        # (the closed-form start may have given it any value) and register again.
        k = target_kinematics(model, q, model.tool, jacobian=False)
        fit = fit_rigid(k.p, measured)
        state = State(model, model.tool, fit.R, fit.t, state.pivot)
    state, _, _ = _least_squares(state, sel, q, measured, w)
    return state


def frames_rms(model: RobotModel, q: Array, measured: Array) -> float:
    """RMS residual (mm) of the model with best-fit frames; joint limits not checked (for
    trying reinterpretations of data that do not fit)."""
    w = np.ones((len(q), 3))
    st = _fit_frames(model, q, measured, w)
    return rms(measured - predict(st, q))


def _expand_fix(specs: tuple[ParameterSpec, ...], fix: Collection[str]) -> frozenset[str]:
    """Parameter names to pin: names, or the groups ``kinematics``, ``tool``, ``frame``."""
    names = {s.name for s in specs}
    out: set[str] = set()
    for item in fix:
        if item == "kinematics":
            out |= {s.name for s in specs if s.kind in KINEMATIC_KINDS}
        elif item in ("tool", "target_offset"):
            out |= {s.name for s in specs if s.kind == "tool"}
        elif item in names:
            out.add(item)
        else:
            raise InputError(
                f"--fix {item}: no such parameter; choose from kinematics, tool, or "
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


def _sigma0(residuals: Array, w: Array, dof: int) -> float:
    return float(np.sqrt(np.sum((residuals * w) ** 2) / max(dof, 1)))


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
) -> CalibrationResult:
    """Identify kinematic errors, target offset and instrument frame together.

    ``q``: joint readings (N×n, rad); ``measured``: target positions in the instrument
    frame (N×3, mm); ``sigma``: their 1σ per axis (N×3, mm) to weight the fit;
    ``robust``: a robust loss (huber, soft_l1, cauchy) after the least-squares fit;
    ``paper_parameters``: the paper's θ, d, a, α on every row (no β); ``fix``: parameter
    names (or ``kinematics``, ``tool``) pinned at nominal. A result that fails an
    acceptance check raises :class:`AcceptanceError` unless ``accept`` (then the failures
    are among the warnings); ``alternatives``: other models to try when diagnosing data
    that do not fit.
    """
    q, measured, sigma = check_measurements(nominal, q, measured, sigma)
    if robust is not None and robust not in ROBUST_LOSSES:
        raise InputError(
            f"unknown robust loss {robust!r}; choose one of {', '.join(ROBUST_LOSSES)}"
        )
    N = len(q)
    if N < 3:
        raise DegenerateGeometryError(f"need at least 3 measurements, got {N}")
    w = _weights(sigma, N)
    warnings: list[str] = []
    accepted: list[str] = []
    specs = parameter_specs(nominal, paper_parameters=paper_parameters)
    pinned = _expand_fix(specs, fix)
    sv = np.linalg.svd(measured - measured.mean(axis=0), compute_uv=False)
    if not sv[1] > 1e-9 * sv[0]:
        raise DegenerateGeometryError(
            "the measurements do not determine the instrument frame (they lie on a line or "
            "at one point); spread the poses over a volume"
        )
    _refuse_or_note(check_data(nominal, q, measured, nominal.tool), accept, warnings, accepted)

    def diagnosis(what: str) -> AcceptanceError:
        return diagnose(nominal, q, measured, frames_rms, alternatives, what=what).refusal()

    try:
        baseline = _fit_frames(nominal, q, measured, w)
    except ConvergenceError:
        raise diagnosis("the registration of the nominal model did not converge") from None
    except MirroredCorrespondenceError:
        raise diagnosis(
            "the nominal model's positions match the measurements only mirrored"
        ) from None
    residuals_before = measured - predict(baseline, q)
    if rms(residuals_before) > ACCURACY_CLASS_MM:
        finding = diagnose(
            nominal,
            q,
            measured,
            frames_rms,
            alternatives,
            what=f"the nominal model with best-fit frames leaves RMS "
            f"{rms(residuals_before):.3g} mm, far worse than any robot's accuracy class",
        )
        _refuse_or_note([finding], accept, warnings, accepted)

    _, J = jacobian(baseline, q, specs)
    Jw_all = (J * w[:, :, None]).reshape(-1, len(specs))
    ident = analyse(Jw_all, specs, fixed=pinned)
    sel = tuple(specs[i] for i in ident.identified)
    if len(sel) >= 3 * N:
        raise InputError(
            f"{N} measurements give {3 * N} equations for {len(sel)} identifiable "
            f"parameters; measure at least {len(sel) // 3 + 1} poses"
        )
    # Identifiability as a matter of degree: fit, estimate the noise, leave at nominal
    # what the noise hides, and fit again from the baseline without it.
    try:
        trial, _, nfev = _least_squares(baseline, sel, q, measured, w)
        point = trial
    except ConvergenceError:
        point, nfev = baseline, 0
    r_trial = measured - predict(point, q)
    _, J = jacobian(point, q, specs)
    ident = weakly_determined(
        (J * w[:, :, None]).reshape(-1, len(specs)),
        _sigma0(r_trial, w, 3 * N - len(sel)),
        ident,
    )
    sel = tuple(specs[i] for i in ident.identified)
    P = len(sel)
    try:
        state, Jw, more = _least_squares(baseline, sel, q, measured, w)
    except ConvergenceError:
        raise diagnosis("the identification did not converge") from None
    nfev += more
    if robust is not None:
        r = np.linalg.norm((measured - predict(state, q)) * w, axis=1)
        f_scale = 2.5 * max(float(np.median(r)) / 1.5382, 1e-12)
        try:
            state, Jw, more = _least_squares(state, sel, q, measured, w, robust, f_scale)
        except ConvergenceError:
            raise diagnosis(f"the robust ({robust}) identification did not converge") from None
        nfev += more
    lost_tool = [s.name for s in specs if s.kind == "tool" and s not in sel]
    if lost_tool:
        warnings.append(
            f"the target offset ({', '.join(lost_tool)}) is not identifiable from these poses "
            "(does the flange orientation never change?); it stays at its nominal value and "
            "the model holds only at the measured orientations"
        )
    _refuse_or_note(
        assess(nominal, estimates_preview(state, nominal, sel), state.tool),
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

    residuals = measured - predict(state, q)
    dof = 3 * N - P
    sigma0 = _sigma0(residuals, w, dof)
    try:
        cov: Array = np.asarray(sigma0**2 * np.linalg.inv(Jw.T @ Jw), dtype=np.float64)
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
        if sp.kind == "tool":
            value = float(state.tool["xyz".index(sp.name[-1])])
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
    tool_std = np.array([e.std for e in estimates if e.kind == "tool"])
    frame_std = _frame_std(state, sel, cov)
    return CalibrationResult(
        nominal=nominal,
        calibrated=state.model,
        tool=state.tool,
        tool_std=tool_std,
        T_instrument_base=state_T(state),
        frame_std=frame_std,
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
    )


def state_T(state: State) -> Array:
    return state.T_instrument_base


def _frame_std(state: State, sel: tuple[ParameterSpec, ...], cov: Array) -> Array:
    """Standard uncertainty of T_instrument_base's rotation vector and translation (at the
    instrument origin), from the covariance of the pivot parameterisation."""
    idx = [k for k, s in enumerate(sel) if s.kind.startswith("frame")]
    if len(idx) != 6:
        return np.full(6, np.nan)
    C = cov[np.ix_(idx, idx)]
    # t = E(ω)(t₀ − pivot) + pivot + δt  ⇒  ∂t/∂ω = −[t₀ − pivot]×, ∂t/∂δt = I.
    G = np.eye(6)
    G[3:6, 0:3] = -skew(state.t - state.pivot)
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
