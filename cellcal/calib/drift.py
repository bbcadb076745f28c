"""Is a calibrated model still good? A check's figures, limits, verdict and cause (pure).

A check measures a few poses and compares them with the model (its geometry, target
offset and sensor frame): each pose's error is the measured position minus the model's
prediction at the reached joints, in the sensor frame (mm).

**Limits.** The model predicts how well it should match new poses: at each check pose
the fit's a-posteriori covariance propagated through the identification Jacobian
(trace(Jₖ C Jₖᵀ)), plus the noise a pose's mean carried when the model was fitted (the
fit's RMS residual, scaled by 3n / dof for the parameters the fit absorbed). Its root
mean square over the check poses is the predicted 1σ RMS error. The covariance holds
the model's error as a distribution; one calibration is one draw of it, which may sit
at 1.5–2× its σ at every pose: the RMS error the calibration measured at its own
held-out poses in the cube (``[validation]`` of the model file) is the second estimate.
Once three or more checks of the model have said ``ok``, the pooled RMS of the first five
of them (the baseline: later ones would let a slow drift widen its own limits) is the
third, and the largest is σ: the warning limit is ``warning_factor`` × σ, the recalibration
limit ``recalibrate_factor`` × σ (defaults 2 and 3), both on the check's RMS error. A
single pose beyond the recalibration limit with the RMS inside is a warning.

**Cause.** When the check is out of its limits, the errors are fitted with each
candidate cause alone — one joint's offset θᵢ, one link length (aᵢ, dᵢ), every length
grown alike (thermal growth), the robot's base or the sensor shifted (3) or moved (6),
the target moved on the flange (3) — through the model's own Jacobian; the candidate
with the smallest χ² + k ln(3N) (Schwarz's criterion, σ per coordinate from the limits)
is named when it leaves no more than the warning limit unexplained. Others that explain
the errors as well are named with it: a check cannot tell a joint-1 offset from the base
turned about that axis, nor d₁ from the base raised.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_model import ParameterSpec, State, jacobian, parameter_specs, predict
from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import InputError

OK, WARNING, RECALIBRATE = "ok", "warning", "recalibrate"
#: earlier checks that said ``ok`` needed before their spread enters the limits, and the
#: most that do: the first ones after the calibration, the baseline (a robot that drifts
#: slowly must not widen its own limits check by check)
MIN_EARLIER = 3
BASELINE = 5
#: a cause is named when it explains at least this fraction of the errors' sum of squares
MIN_EXPLAINED = 0.8


@dataclass(frozen=True)
class ModelUncertainty:
    """What a calibrated model says of its own uncertainty: the covariance (internal
    units, mm and rad) of its identified parameters ``specs``, the point the sensor
    frame's rotation turns about (sensor frame, mm), the 1σ noise of one pose's
    measured mean when it was fitted (3-D RMS, mm), and its validation."""

    specs: tuple[ParameterSpec, ...]
    covariance: Array
    pivot: Array
    noise_mm: float
    #: the RMS error its calibration measured at held-out poses in the cube (None: not
    #: in the file — a model of ``cellcal calibrate``)
    validation_mm: float | None = None


@dataclass(frozen=True)
class Limits:
    """A check's control limits (mm, on its RMS error): ``predicted_mm`` from the model's
    own uncertainty, ``validation_mm`` what its calibration measured at held-out poses
    in the cube, ``earlier_mm`` the pooled RMS of earlier ``ok`` checks (None: fewer
    than :data:`MIN_EARLIER`), ``sigma_mm`` the largest, and the two limits."""

    predicted_mm: float
    validation_mm: float | None
    earlier_mm: float | None
    sigma_mm: float
    warning_mm: float
    limit_mm: float
    n_earlier: int


@dataclass(frozen=True)
class Cause:
    """A candidate cause fitted to the errors: its words, its parameters' values (mm,
    deg, ppm as named), the fraction of the errors' sum of squares it explains and the
    RMS it leaves (mm)."""

    name: str
    text: str
    values: dict[str, float]
    explained: float
    left_mm: float


@dataclass(frozen=True)
class Diagnosis:
    """The most likely cause (None: no single cause explains the errors) and the others
    that explain them as well."""

    cause: Cause | None
    alternatives: tuple[Cause, ...]

    @property
    def sentence(self) -> str | None:
        if self.cause is None:
            return None
        text = f"{self.cause.text} (explains {100 * self.cause.explained:.0f} % of the error)"
        if self.alternatives:
            others = "; or ".join(a.text for a in self.alternatives)
            text += f"; or {others} (a check cannot tell them apart)"
        return text


def model_state(
    model: RobotModel, target_offset: Array, T_sensor_base: Array, pivot: Array
) -> State:
    T = np.asarray(T_sensor_base, dtype=np.float64)
    return State(model, np.asarray(target_offset, dtype=np.float64), T[:3, :3], T[:3, 3], pivot)


def pose_errors(
    state: State, q: Array, measured: Array, conditions: Conditions | None = None
) -> Array:
    """Measured minus predicted target positions (N×3, sensor frame, mm), the model's
    error terms at the check's ``conditions`` (its temperatures: a drift with time ran
    during the calibration's own campaign, not since)."""
    out: Array = np.asarray(measured, dtype=np.float64) - predict(state, q, None, conditions)
    return out


def rms(errors: Array) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(errors) ** 2, axis=1))))


def predicted_rms(state: State, q: Array, u: ModelUncertainty) -> float:
    """The model's predicted RMS error at the poses ``q`` (rad): its parameters'
    uncertainty there and the noise of a pose's mean, in quadrature (mm)."""
    names = {s.name: s for s in parameter_specs(state.model)}
    missing = [s.name for s in u.specs if s.name not in names]
    if missing:
        raise InputError(
            f"the model's covariance names {missing[0]!r}, which its geometry does not have"
        )
    _, J = jacobian(state, np.atleast_2d(q), u.specs)
    var = np.einsum("nip,pq,niq->n", J, u.covariance, J)
    return float(math.sqrt(max(float(np.mean(var)), 0.0) + u.noise_mm**2))


def control_limits(
    predicted_mm: float,
    validation_mm: float | None,
    earlier_rms_mm: Sequence[float],
    warning_factor: float,
    recalibrate_factor: float,
) -> Limits:
    """The limits from the model's prediction, its validation and the earlier ``ok``
    checks' RMS (oldest first: the first :data:`BASELINE` count)."""
    earlier = None
    if len(earlier_rms_mm) >= MIN_EARLIER:
        earlier = float(np.sqrt(np.mean(np.square(earlier_rms_mm[:BASELINE]))))
    sigma = max(predicted_mm, validation_mm or 0.0, earlier or 0.0)
    return Limits(
        predicted_mm,
        validation_mm,
        earlier,
        sigma,
        warning_factor * sigma,
        recalibrate_factor * sigma,
        min(len(earlier_rms_mm), BASELINE),
    )


def verdict(errors_mm: Sequence[float], limits: Limits) -> str:
    """``recalibrate`` when the RMS error is beyond the recalibration limit, ``warning``
    beyond the warning limit or with one pose beyond the recalibration limit, else ``ok``."""
    e = np.asarray(errors_mm, dtype=np.float64)
    value = float(np.sqrt(np.mean(e**2)))
    if value > limits.limit_mm:
        return RECALIBRATE
    if value > limits.warning_mm or float(e.max()) > limits.limit_mm:
        return WARNING
    return OK


def _vector(v: Array, digits: int) -> str:
    return "(" + ", ".join(f"{x:+.{digits}f}" for x in v) + ")"


def _candidates(state: State, q: Array) -> list[tuple[str, Array, list[str]]]:
    """Each candidate cause: its name, its columns of the Jacobian (3N×k, internal
    units) and its parameters' names."""
    specs = parameter_specs(state.model)
    _, J = jacobian(state, q, specs)
    A = J.reshape(-1, len(specs))
    col = {s.name: k for k, s in enumerate(specs)}
    out: list[tuple[str, Array, list[str]]] = []
    for i in range(1, state.model.dof + 1):
        out.append((f"theta{i}", A[:, [col[f"theta{i}"]]], [f"theta{i}"]))
    lengths = []
    for i, joint in enumerate(state.model.joints, start=1):
        for kind in ("a", "d"):
            name = f"{kind}{i}"
            if name not in col:  # a row with β has no d
                continue
            out.append((name, A[:, [col[name]]], [name]))
            lengths.append((col[name], float(getattr(joint, kind))))  # grows by ε·L
    growth = np.zeros(A.shape[0])
    for k, length in lengths:
        growth += A[:, k] * length * 1e-6  # per ppm
    if np.any(growth):
        out.append(("growth", growth[:, None], ["ppm"]))
    shift = [col[f"frame_{c}"] for c in "xyz"]
    turn = [col[f"frame_r{c}"] for c in "xyz"]
    out.append(("frame_shift", A[:, shift], ["frame_x", "frame_y", "frame_z"]))
    out.append(("frame_move", A[:, turn + shift], [specs[k].name for k in turn + shift]))
    tool = [col[f"target_offset_{c}"] for c in "xyz"]
    out.append(("target", A[:, tool], [specs[k].name for k in tool]))
    return out


def _describe(name: str, x: Array, state: State) -> tuple[str, dict[str, float]]:
    R_base_sensor = state.R.T
    if name.startswith("theta"):
        deg = math.degrees(float(x[0]))
        return f"joint {name[5:]} offset {deg:+.4f}°", {name: deg}
    if name == "growth":
        return (
            f"every link length grown {float(x[0]):+.0f} ppm (thermal growth?)",
            {"ppm": float(x[0])},
        )
    if name == "frame_shift":
        shift = R_base_sensor @ x
        return (
            f"the robot's base or the sensor shifted {_vector(shift, 3)} mm (robot base axes)",
            dict(zip(("x_mm", "y_mm", "z_mm"), map(float, shift), strict=True)),
        )
    if name == "frame_move":
        turn = np.degrees(R_base_sensor @ x[:3])
        shift = R_base_sensor @ x[3:]
        values = dict(zip(("rx_deg", "ry_deg", "rz_deg"), map(float, turn), strict=True))
        values |= dict(zip(("x_mm", "y_mm", "z_mm"), map(float, shift), strict=True))
        return (
            f"the robot's base or the sensor moved: turned {_vector(turn, 4)}° and shifted "
            f"{_vector(shift, 3)} mm (robot base axes)",
            values,
        )
    if name == "target":
        return (
            f"the target moved on the flange {_vector(x, 3)} mm (flange axes)",
            dict(zip(("x_mm", "y_mm", "z_mm"), map(float, x), strict=True)),
        )
    return f"link {name} changed {float(x[0]):+.3f} mm", {name: float(x[0])}


def diagnose(
    state: State, q: Array, errors: Array, sigma_mm: float, warning_mm: float
) -> Diagnosis:
    """Which single cause explains the errors (N×3, sensor frame) at the poses ``q``;
    ``sigma_mm`` is the 1σ RMS error expected (per pose, 3-D), ``warning_mm`` what a
    cause may leave unexplained."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    n = len(q)
    total = float(e @ e)
    if total == 0 or n == 0:
        return Diagnosis(None, ())
    per_coordinate = max(sigma_mm, 1e-9) / math.sqrt(3)
    scored = []
    for name, A, _ in _candidates(state, q):
        scale = np.linalg.norm(A, axis=0)
        if not np.all(scale > 0):
            continue
        x_scaled, *_ = np.linalg.lstsq(A / scale, e, rcond=None)
        x = x_scaled / scale
        r = e - A @ x
        left = float(r @ r)
        score = left / per_coordinate**2 + A.shape[1] * math.log(3 * n)
        text, values = _describe(name, x, state)
        cause = Cause(name, text, values, 1 - left / total, math.sqrt(left / n))
        scored.append((score, cause))
    scored.sort(key=lambda sc: sc[0])
    good = [c for _, c in scored if c.left_mm <= warning_mm and c.explained >= MIN_EXPLAINED]
    if not good or good[0] is not scored[0][1]:
        return Diagnosis(None, ())
    # a moved base (turned and shifted) says nothing more than a shifted one
    names = {c.name for c in good}
    others = [c for c in good[1:] if not (c.name == "frame_move" and "frame_shift" in names)]
    return Diagnosis(good[0], tuple(others[:2]))
