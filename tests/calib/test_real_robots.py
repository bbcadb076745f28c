"""Calibration on public laser-tracker data of real robots (tests/data/real, MIT):
held-out accuracy, and parameters a real robot can have.

The numbers asserted are what these data allow, with margin: on the UR5 the nominal
model with best-fit frames predicts the 20 separate test poses to 0.56 mm RMS and the
calibrated model to 0.10 mm; on the cable-driven Barrett WAM (repeatability about 2 mm)
4.7 mm and 3.7 mm.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.acceptance import TOLERANCE_DEG, TOLERANCE_MM
from cellcal.calib.identification import CalibrationResult, calibrate
from cellcal.calib.validation import Validation, validate_on
from cellcal.files.measurements import read_measurements
from cellcal.files.models import load_model

REAL = Path(__file__).parents[1] / "data" / "real"


@cache
def _calibrated(robot: str) -> tuple[CalibrationResult, Validation]:
    nominal = load_model(str(REAL / robot / "model.toml")).model
    data = read_measurements(REAL / robot / "measurements.csv", nominal.dof)
    val = read_measurements(REAL / robot / "validation.csv", nominal.dof)
    res = calibrate(nominal, data.q, data.xyz)
    return res, validate_on(res, data.q, data.xyz, val.q, val.xyz)


def _plausible(res: CalibrationResult, mm: float, deg: float) -> None:
    for p in res.parameters:
        if p.identified and p.kind != "target_offset":
            limit = deg if p.unit == "deg" else mm
            assert abs(p.value) < limit, p


def test_ur5_held_out_accuracy_and_plausible_parameters():
    res, v = _calibrated("ur5")
    assert v.before.rms > 0.4
    assert v.after.rms < 0.13
    assert v.improvement > 4.0
    # Every correction a real UR5 can have: below a millimetre and a degree.
    _plausible(res, 1.0, 1.0)
    # θ5 and α5 are identifiable in rank but hidden by the noise: left at nominal, named.
    weak = {p.name for p in res.parameters if p.at_nominal == "weak"}
    assert {"theta5", "alpha5"} <= weak
    # The target (an SMR 31 mm off the flange nominally) stays on the flange axis.
    assert np.hypot(res.target_offset[0], res.target_offset[1]) < 1.0
    assert 25.0 < res.target_offset[2] < 40.0


def test_ur5_without_degree_of_identifiability_fits_absurd_values(monkeypatch):
    """What the exact-rank selection alone did: α5 about −27°, a5 about −49 mm, for the
    same held-out accuracy. The acceptance check refuses that model."""
    import cellcal.calib.identification as ident
    from cellcal.errors import AcceptanceError

    monkeypatch.setattr(ident, "weakly_determined", lambda J, s, i: i)
    nominal = load_model(str(REAL / "ur5" / "model.toml")).model
    data = read_measurements(REAL / "ur5" / "measurements.csv", nominal.dof)
    with pytest.raises(AcceptanceError, match="alpha5"):
        calibrate(nominal, data.q, data.xyz)


def test_barrett_wam_seven_axes():
    res, v = _calibrated("barrett-wam")
    assert res.nominal.dof == 7
    assert v.after.rms < v.before.rms * 0.9
    _plausible(res, TOLERANCE_MM, TOLERANCE_DEG)


@cache
def _with_terms(robot: str) -> tuple[CalibrationResult, Validation]:
    nominal = load_model(str(REAL / robot / "model.toml")).model
    data = read_measurements(REAL / robot / "measurements.csv", nominal.dof)
    val = read_measurements(REAL / robot / "validation.csv", nominal.dof)
    res = calibrate(nominal, data.q, data.xyz, terms="auto", accept=True)
    return res, validate_on(res, data.q, data.xyz, val.q, val.xyz)


def test_ur5_harmonics_pass_blocked_cross_validation_and_beat_geometry():
    """The issue's goal: held-out mean ≤ 0.088 mm (geometric 0.101) on the source's own
    test poses, with only terms blocked cross-validation accepts."""
    res, v = _with_terms("ur5")
    _, geometric = _calibrated("ur5")
    assert res.term_choice is not None and res.term_choice.accepted == ("harmonics",)
    assert res.term_choice.final_cv_mm < 0.7 * res.term_choice.geometric_cv_mm
    assert v.after.mean <= 0.088 < geometric.after.mean
    # the cyclic errors the data show: 13 times per turn of joint 1 (the strongest, the
    # first found), 26 of joint 2, beside others
    regs = {t.joint: t.regressors for t in res.calibrated.terms}
    cyclic = {j: [r for r in names if r[3:] not in ("1", "2")] for j, names in regs.items()}
    assert cyclic[1][:2] == ["sin13", "cos13"] and {"sin26", "cos26"} <= set(cyclic[2])


def test_wam_takes_gravity_and_ratio_and_meets_its_goal():
    """The issue's goal: the WAM's test-pose mean ≤ 2.9 mm (geometric 3.48), with only
    terms blocked cross-validation accepts: gravity and the cable drives' ratio errors
    (a few tenths of a percent on joints 1–3), not the harmonics."""
    res, v = _with_terms("barrett-wam")
    _, geometric = _calibrated("barrett-wam")
    assert res.term_choice is not None and res.term_choice.accepted == ("gravity", "ratio")
    assert "harmonics" not in res.term_choice.accepted
    assert v.after.mean <= 2.9 < geometric.after.mean
    assert {t.name for t in res.calibrated.terms} == {"gravity", "ratio"}
    ratios = {t.joint: t for t in res.calibrated.terms if t.name == "ratio"}
    assert set(ratios) == {1, 2, 3}
    for t in ratios.values():  # each several σ from zero, each below half a percent
        assert 2.5 * t.sigma[0] < -t.coefficients[0] < 0.005
