"""Validation: position errors on points the calibration did not see.

"Before" is always the nominal geometry with the best-fit sensor frame and target
offset, fitted on the same calibration points as "after"; both predict the held-out
points. k-fold cross-validation fits k times, each time holding one fold out.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.acceptance import ACCURACY_CLASS_MM
from cellcal.calib.error_model import Groups, Index, label_index, predict
from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.identification import (
    CalibrationResult,
    calibrate,
    fit_frames,
)
from cellcal.calib.observations import check_measurements, on_a_line
from cellcal.calib.registration_batch import fit_rigid_batch
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.term_choice import TermRequest
from cellcal.errors import AcceptanceError, InputError, UserError


@dataclass(frozen=True)
class ErrorStats:
    """Statistics of position-error lengths (mm)."""

    n: int
    mean: float
    rms: float
    max: float
    p95: float

    @classmethod
    def of(cls, errors: Array) -> ErrorStats:
        d = np.linalg.norm(np.atleast_2d(errors), axis=1)
        return cls(
            n=int(d.size),
            mean=float(d.mean()),
            rms=float(np.sqrt(np.mean(d * d))),
            max=float(d.max()),
            p95=float(np.percentile(d, 95)),
        )


@dataclass(frozen=True)
class Validation:
    """Held-out errors before and after calibration; ``method`` says how they were held
    out (``k-fold k=5`` or ``file``); ``errors_before``/``errors_after`` per point (N×3)."""

    method: str
    before: ErrorStats
    after: ErrorStats
    errors_before: Array
    errors_after: Array

    @property
    def improvement(self) -> float:
        """before.rms / after.rms."""
        return self.before.rms / self.after.rms if self.after.rms > 0 else float("inf")


def held_out_groups(
    result: CalibrationResult,
    n: int,
    targets: Sequence[str] | None = None,
    sessions: Sequence[str] | None = None,
) -> Groups:
    """The calibration's targets and sessions of held-out rows, by their labels (None: the
    first of each). A label the calibration did not see is refused: a new target has no
    offset yet and a new session is another set-up, to be re-registered."""

    def index(labels: Sequence[str] | None, known: tuple[str, ...], what: str) -> Index:
        idx, unknown = label_index(n, labels, known)
        if unknown is not None:
            hint = (
                "another set-up: re-register it with cellcal calibrate --model CALIBRATED.toml "
                "--fix kinematics --data FILE"
                if what == "session"
                else "its offset was not calibrated"
            )
            raise InputError(
                f"the validation points name {what} {unknown!r}, which the calibration data "
                f"do not have ({', '.join(repr(k) for k in known)}): {hint}"
            )
        return idx

    return Groups(
        index(targets, result.targets, "target"),
        index(sessions, result.sessions, "session"),
        result.targets,
        result.sessions,
    )


def validate_on(
    result: CalibrationResult,
    q_calibration: Array,
    measured_calibration: Array,
    q: Array,
    measured: Array,
    sigma_calibration: Array | None = None,
    groups: Groups | None = None,
    conditions: Conditions | None = None,
) -> Validation:
    """Errors of the calibrated model and of the baseline on separately measured points;
    ``groups``: their targets and sessions among the calibration's (see
    :func:`held_out_groups`); ``conditions``: their time, temperature and payload."""
    q, measured, _ = check_measurements(result.nominal, q, measured, None)
    baseline = fit_frames(
        result.nominal, q_calibration, measured_calibration, sigma_calibration, result.groups
    )
    eb = measured - predict(baseline, q, groups)
    ea = measured - result.predict(q, groups, conditions)
    off = ErrorStats.of(ea).rms
    if off > ACCURACY_CLASS_MM and len(q) >= 4:
        # Far off: is it the model, or were these points measured from somewhere else?
        try:
            one = None
            if groups is not None:  # the same targets, one new sensor frame
                one = Groups(groups.target, np.zeros(len(q), dtype=np.intp), groups.targets)
            own = ErrorStats.of(
                measured - predict(fit_frames(result.calibrated, q, measured, None, one), q, one)
            )
        except UserError:
            own = None
        line = on_a_line(measured)
        if own is None and line is not None:
            # a rigid fit still says whether they fit once moved; the rotation about the
            # line is free and does not change what is left
            fit = fit_rigid_batch(result.predict(q, groups)[None], measured[None])
            own = ErrorStats.of(np.zeros((1, 3)) + float(fit.rms[0]))
        if own is not None and own.rms < ACCURACY_CLASS_MM:
            how = (
                "re-register that set-up with cellcal calibrate --model CALIBRATED.toml "
                "--fix kinematics --data FILE"
                if line is None
                else f"and {line.reason()}, so they cannot be re-registered: validate on "
                "points spread over a plane or a volume"
            )
            raise InputError(
                f"the validation points are {off:.0f} mm (RMS) from the model's prediction but "
                f"fit it within {own.rms:.3g} mm once re-registered: they come from another "
                f"set-up (sensor moved, another target); {how}"
            )
        raise AcceptanceError(
            "validation far off",
            f"the validation points are {off:.0f} mm (RMS) from the model's prediction, "
            f"beyond any robot's accuracy class ({ACCURACY_CLASS_MM:.0f} mm), and no "
            "re-registration brings them close: they are not this robot's in this set-up "
            "(another robot or model, other units, other joint zeros)",
        )
    return Validation("file", ErrorStats.of(eb), ErrorStats.of(ea), eb, ea)


def cross_validate(
    nominal: RobotModel,
    q: Array,
    measured: Array,
    sigma: Array | None = None,
    *,
    folds: int = 5,
    seed: int = 0,
    robust: str | None = None,
    paper_parameters: bool = False,
    fix: Collection[str] = (),
    groups: Groups | None = None,
    orientations: Array | None = None,
    terms: str | TermRequest = "geometric",
    conditions: Conditions | None = None,
) -> Validation:
    """k-fold cross-validation: every point is predicted by a calibration without it,
    made with the same options as the calibration it validates (a fold is not refused by
    the acceptance checks: the calibration on all points was checked)."""
    q, measured, sigma = check_measurements(nominal, q, measured, sigma)
    N = len(q)
    g = groups if groups is not None else Groups.single(N)
    if folds < 2 or folds > N:
        raise InputError(f"folds must be between 2 and the number of points ({N}), got {folds}")
    order = np.random.default_rng(seed).permutation(N)
    eb = np.empty((N, 3))
    ea = np.empty((N, 3))
    for k in range(folds):
        held = order[k::folds]
        train = np.setdiff1d(order, held)
        s = None if sigma is None else sigma[train]
        res = calibrate(
            nominal,
            q[train],
            measured[train],
            s,
            robust=robust,
            paper_parameters=paper_parameters,
            fix=fix,
            accept=True,
            groups=g.subset(train),
            orientations=None if orientations is None else orientations[train],
            terms=terms,
            conditions=None if conditions is None else conditions.subset(train),
        )
        base = fit_frames(nominal, q[train], measured[train], s, g.subset(train))
        eb[held] = measured[held] - predict(base, q[held], g.subset(held))
        at = None if conditions is None else conditions.subset(held)
        ea[held] = measured[held] - res.predict(q[held], g.subset(held), at)
    return Validation(f"k-fold k={folds}", ErrorStats.of(eb), ErrorStats.of(ea), eb, ea)
