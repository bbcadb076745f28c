"""Acceptance checks: results that cannot be right are refused, with their likely cause.

A calibration can fit nonsense: a tracker that measures a fixed reflector, positions in
metres, joint readings in radians, a flipped joint sign or the wrong robot model all
give a "result" if nothing looks at it. These checks compare the data and the result
with what a real robot can do, and each failure is a :class:`AcceptanceError` that names
the check and what usually causes it (exit 3 at the command line).

* before the fit (:func:`check_data`), from the scale of the data against the model:
  the target must follow the robot, positions must be millimetres and joint readings
  degrees, and the arm must move enough for the geometry to show;
* when the fit fails or the nominal model is far off (:func:`diagnose`), the obvious
  reinterpretations are tried — radians, metres, each joint's sign, the other built-in
  models — and the one that fits is named;
* after the fit (:func:`assess`): corrections within manufacturing tolerances and a
  target offset on the flange; the registration of the nominal model must be within any
  robot's accuracy class (:data:`ACCURACY_CLASS_MM`, checked by the identification).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import AcceptanceError, CellcalError

#: RMS residual of the nominal model with best-fit frames above which no robot of any
#: accuracy class explains the data (uncalibrated industrial arms: 0.5–5 mm).
ACCURACY_CLASS_MM = 25.0
#: Identified corrections beyond these are not manufacturing errors (a wrong model,
#: units or signs); real robots' errors are below a few mm and a fraction of a degree.
TOLERANCE_MM = 10.0
TOLERANCE_DEG = 2.0
#: The measured target must move at least this fraction of the model's motion.
FOLLOWS_RATIO = 0.2
#: The arm (wrist centre) must span at least this fraction of the robot's reach.
ARM_SPAN_FRACTION = 0.01

CHECK_FOLLOWS = "target does not follow the robot"
CHECK_UNITS = "units"
CHECK_SPAN = "poses too close"
CHECK_TOLERANCE = "corrections beyond manufacturing tolerances"
CHECK_TARGET = "target offset off the flange"
CHECK_REGISTRATION = "nominal registration"
CHECK_CONVERGENCE = "no convergence"


@dataclass(frozen=True)
class Finding:
    """A failed acceptance check: its name and the one-line explanation."""

    check: str
    message: str

    def refusal(self) -> AcceptanceError:
        return AcceptanceError(self.check, self.message)


def spread(p: Array) -> float:
    """RMS distance of points from their centroid (mm)."""
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def reach(model: RobotModel) -> float:
    """A robot's size: the sum of its link lengths and offsets (mm)."""
    return float(sum(math.hypot(j.a, j.d) for j in model.joints))


def _positions(model: RobotModel, q: Array, target_offset: Array) -> Array:
    p: Array = target_kinematics(model, q, target_offset, jacobian=False).p
    return p


def _arm_span(model: RobotModel, q: Array) -> float:
    """Spread of the wrist (the origin of the last three joints' first frame)."""
    k = max(model.dof - 3, 1)
    arm = RobotModel(model.name, model.convention, model.joints[:k], parallel=model.parallel[:k])
    return spread(_positions(arm, q[:, :k], np.zeros(3)))


def looks_like_radians(q: Array) -> bool:
    """Joint readings (rad, converted from the file's degrees) that never leave ±2π°."""
    return bool(np.max(np.abs(np.degrees(q))) <= 2 * math.pi + 1e-6)


def check_data(model: RobotModel, q: Array, measured: Array, target_offset: Array) -> list[Finding]:
    """Checks of the data against the model, before any fit (``q`` rad, ``measured`` mm)."""
    predicted = _positions(model, q, target_offset)
    s_model = spread(predicted)
    s_meas = spread(measured)
    found: list[Finding] = []
    if looks_like_radians(q) and len(q) > 3:
        q_rad = np.degrees(q)  # the file's numbers, read as radians
        s_alt = spread(_positions(model, q_rad, target_offset))
        if s_alt > 0 and 0.5 < s_meas / s_alt < 2.0 and not 0.5 < s_meas / s_model < 2.0:
            found.append(
                Finding(
                    CHECK_UNITS,
                    "the joint readings look like radians (none exceeds ±6.3 and the target "
                    f"moves {s_meas:.0f} mm, as it would if they were radians); the "
                    "measurement CSV takes degrees",
                )
            )
            return found
    span = _arm_span(model, q)
    if span < ARM_SPAN_FRACTION * reach(model):
        found.append(
            Finding(
                CHECK_SPAN,
                f"the arm moves only {span:.3g} mm between the poses of a robot of "
                f"{reach(model):.0f} mm reach; was the cube edge or region given in metres "
                "(0.2 for 200 mm)?",
            )
        )
        return found
    ratio = s_meas / s_model if s_model > 0 else math.inf
    if 1 / 3000 < ratio < 1 / 300:
        found.append(
            Finding(
                CHECK_UNITS,
                f"the measured positions span {ratio:.2g}× the robot's motion: they look "
                "like metres; the measurement CSV takes millimetres",
            )
        )
    elif ratio < FOLLOWS_RATIO:
        found.append(
            Finding(
                CHECK_FOLLOWS,
                f"the measured target moves {s_meas:.3g} mm (RMS about its centroid) while "
                f"the model moves it {s_model:.0f} mm: the sensor sees something else (a "
                "fixed reflector, another cell, a stale value) or the joints are not the "
                "robot's",
            )
        )
    elif ratio > 1 / FOLLOWS_RATIO:
        unit = " (micrometres?)" if 300 < ratio < 3000 else ""
        found.append(
            Finding(
                CHECK_UNITS,
                f"the measured positions span {ratio:.3g}× the robot's motion{unit}: check "
                "the units of the positions (mm) and of the joints (deg), and the model",
            )
        )
    return found


@dataclass(frozen=True)
class Reading:
    """One reinterpretation of the data: a label and how it turns (q, measured)."""

    label: str
    q: Array
    measured: Array
    model: RobotModel


def _readings(
    model: RobotModel, q: Array, measured: Array, others: Sequence[RobotModel]
) -> list[Reading]:
    out = [Reading("as given", q, measured, model)]
    if looks_like_radians(q):
        out.append(Reading("joint readings in radians", np.degrees(q), measured, model))
    out.append(Reading("positions in metres", q, measured * 1000.0, model))
    for j in range(model.dof):
        flipped = q.copy()
        flipped[:, j] *= -1.0
        out.append(Reading(f"joint {j + 1} with the opposite sign", flipped, measured, model))
    for other in others:
        if other.dof == model.dof and other.name != model.name:
            out.append(Reading(f"the model {other.name}", q, measured, other))
    return out


def diagnose(
    model: RobotModel,
    q: Array,
    measured: Array,
    fit_rms: Callable[[RobotModel, Array, Array], float],
    others: Sequence[RobotModel] = (),
    *,
    what: str,
) -> Finding:
    """Why the data do not fit: try the obvious reinterpretations and name the one that
    fits the nominal model (``fit_rms``: RMS of a frames-only fit, mm). ``what`` says what
    failed ("the identification did not converge", …)."""
    scores: list[tuple[float, str]] = []
    for r in _readings(model, q, measured, others):
        try:
            rms = fit_rms(r.model, r.q, r.measured)
        except (CellcalError, np.linalg.LinAlgError, ValueError):
            continue
        if math.isfinite(rms):
            scores.append((rms, r.label))
    given = next((s for s, label in scores if label == "as given"), math.inf)
    others_ = sorted((s, label) for s, label in scores if label != "as given")
    if others_ and others_[0][0] < ACCURACY_CLASS_MM and others_[0][0] < given / 5:
        rms, label = others_[0]
        return Finding(
            CHECK_CONVERGENCE if "converge" in what else CHECK_REGISTRATION,
            f"{what}; the data fit the nominal model with {label} (RMS {rms:.3g} mm, "
            f"against {given:.3g} mm as given): fix the data or the model",
        )
    return Finding(
        CHECK_CONVERGENCE if "converge" in what else CHECK_REGISTRATION,
        f"{what}{'' if 'RMS' in what else f' (nominal model, best-fit frames: RMS {given:.3g} mm)'}"
        "; no simple "
        "reinterpretation (radians, metres, a joint's sign, another built-in model) fits: "
        "check that the joints and the positions were recorded at the same instants, the "
        "joint order, and that the wrist orientation varies between poses",
    )


def assess(
    model: RobotModel,
    corrections: Sequence[tuple[str, str, float]],
    target_offset: Array,
) -> list[Finding]:
    """Checks of a finished fit: ``corrections`` (name, unit, value in mm or deg) of the
    identified kinematic parameters, and the target offset (mm)."""
    found: list[Finding] = []
    big = [
        (n, u, v)
        for n, u, v in corrections
        if (u == "mm" and abs(v) > TOLERANCE_MM) or (u == "deg" and abs(v) > TOLERANCE_DEG)
    ]
    if big:
        shown = ", ".join(f"{n} {v:+.3g} {u}" for n, u, v in big[:4])
        found.append(
            Finding(
                CHECK_TOLERANCE,
                f"{shown} (real robots: below {TOLERANCE_MM:g} mm and {TOLERANCE_DEG:g}°); "
                "usually the wrong model (--model), joint order or sign, or units",
            )
        )
    if float(np.linalg.norm(target_offset)) > reach(model):
        found.append(
            Finding(
                CHECK_TARGET,
                f"the target is estimated {float(np.linalg.norm(target_offset)):.0f} mm from the "
                f"flange, beyond the robot's {reach(model):.0f} mm reach: the target does "
                "not move with the flange, or the poses do not determine it",
            )
        )
    return found
