"""The k-fold choice among noise-hidden parameters (cellcal.calib.parameter_choice)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import cellcal.calib.identification as identification
from cellcal.calib.acceptance import TOLERANCE_DEG, TOLERANCE_MM
from cellcal.calib.error_model import predict
from cellcal.calib.identification import calibrate
from cellcal.calib.parameter_choice import Choice
from cellcal.calib.validation import validate_on
from cellcal.files.measurements import read_measurements
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import TrueCell, measure, random_cell, random_joints

REAL = Path(__file__).parents[1] / "data" / "real"
KR5 = load_model("kuka-kr5-arc").model


def _wrist_error_cell(seed: int) -> tuple[TrueCell, np.random.Generator]:
    """A KR 5 arc with small errors everywhere and a real 1.5° error in α5 (1° in θ4)."""
    rng = np.random.default_rng(seed)
    cell = random_cell(KR5, rng)
    j = list(cell.model.joints)
    j[4] = replace(j[4], alpha=j[4].alpha + math.radians(1.5))
    j[3] = replace(j[3], theta=j[3].theta + math.radians(1.0))
    return TrueCell(cell.model.with_joints(tuple(j)), cell.target_offset, cell.T_sensor_base), rng


def _rule_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(
        identification,
        "choose",
        lambda ident, *_: Choice(ident, (), math.nan, math.nan, ()),
    )


@pytest.mark.parametrize("seed", [0, 5])
def test_a_real_error_the_noise_hid_is_freed_and_predicts_better(monkeypatch, seed):
    """Noisy data over a small joint range: the rule hides α5 (its σ exceeds 0.1°), but
    its 1.5° error is real. The k-fold error frees it, and the model predicts new poses
    closer to the truth than the rule's."""
    cell, rng = _wrist_error_cell(seed)
    q = random_joints(KR5, rng, 40, span=0.25)
    m = measure(cell, q, rng, 0.1)
    q_new = random_joints(KR5, rng, 300, span=0.25)
    truth = cell.positions(q_new)

    res = calibrate(KR5, q, m)
    c = res.parameter_choice
    assert c is not None and "alpha5" in c.freed
    assert c.chosen_mm < c.rule_mm
    alpha5 = next(p for p in res.parameters if p.name == "alpha5")
    assert alpha5.identified and abs(alpha5.value - 1.5) < 3 * alpha5.std + 0.3

    with monkeypatch.context() as mp:
        _rule_only(mp)
        rule = calibrate(KR5, q, m)
    assert "alpha5" in [p.name for p in rule.parameters if p.at_nominal == "weak"]

    def err(r: identification.CalibrationResult) -> float:
        return float(np.sqrt(np.mean(np.sum((predict(r.state, q_new) - truth) ** 2, axis=1))))

    assert err(res) < 0.8 * err(rule)


def test_the_wam_keeps_its_plausible_model_and_says_what_would_lower_the_error():
    """The real Barrett WAM: only freeing α5 lowers the k-fold error, and it puts α5
    beyond 2°; the rule's set stays, every correction within tolerance, and a warning
    names α5 with both figures."""
    nominal = load_model(str(REAL / "barrett-wam" / "model.toml")).model
    data = read_measurements(REAL / "barrett-wam" / "measurements.csv", nominal.dof)
    val = read_measurements(REAL / "barrett-wam" / "validation.csv", nominal.dof)
    res = calibrate(nominal, data.q, data.xyz)
    c = res.parameter_choice
    assert c is not None and c.freed == ()
    assert [n for n, _ in c.tempting] == ["alpha5"]
    tried = {n: (cv, ok) for n, cv, ok in c.tried}
    assert not tried["alpha5"][1] and tried["alpha5"][0] < 0.97 * c.rule_mm
    assert any("alpha5" in w and "beyond manufacturing tolerance" in w for w in res.warnings)
    for p in res.parameters:
        if p.identified and p.kind != "target_offset":
            assert abs(p.value) <= (TOLERANCE_DEG if p.unit == "deg" else TOLERANCE_MM), p
    v = validate_on(res, data.q, data.xyz, val.q, val.xyz)
    assert v.after.rms < v.before.rms


def test_the_ur5_keeps_theta5_and_alpha5_at_nominal():
    nominal = load_model(str(REAL / "ur5" / "model.toml")).model
    data = read_measurements(REAL / "ur5" / "measurements.csv", nominal.dof)
    res = calibrate(nominal, data.q, data.xyz)
    c = res.parameter_choice
    assert c is not None and c.freed == ()
    assert {p.name for p in res.parameters if p.at_nominal == "weak"} == {"theta5", "alpha5"}


def test_no_choice_without_hidden_parameters():
    rng = np.random.default_rng(3)
    cell = random_cell(KR5, rng)
    q = random_joints(KR5, rng, 80)
    res = calibrate(KR5, q, measure(cell, q, rng, 0.01))
    assert res.parameter_choice is None


def test_the_one_pass_kfold_error_is_what_refitting_each_fold_gives():
    """kfold_rms takes one Gauss–Newton step per fold from the fit to all poses; fitting
    each fold's complement to convergence gives the same figure."""
    from cellcal.calib import levenberg
    from cellcal.calib.error_model import Groups, parameter_specs
    from cellcal.calib.identifiability import analyse
    from cellcal.calib.observations import Data, initial_state
    from cellcal.calib.parameter_choice import FOLDS, kfold_rms

    cell, rng = _wrist_error_cell(1)
    q = random_joints(KR5, rng, 60, span=0.4)
    m = measure(cell, q, rng, 0.05)
    g = Groups.single(len(q))
    data = Data(q, m, g)
    w = np.ones((len(q), 3))
    start = initial_state(KR5, q, m, g)
    specs = parameter_specs(KR5, groups=g)
    ident = analyse(levenberg.linearise(start, specs, data, w).R, specs)
    sel = tuple(specs[i] for i in ident.identified)
    full = levenberg.fit(start, sel, data, w).state
    total = 0.0
    for k in range(FOLDS):
        test = np.arange(k, len(q), FOLDS)
        train = np.setdiff1d(np.arange(len(q)), test)
        st = levenberg.fit(full, sel, data.subset(train), w[train]).state
        total += float(np.sum(data.subset(test).residuals(st) ** 2))
    refit = math.sqrt(total / len(q))
    assert kfold_rms(full, sel, data, w) == pytest.approx(refit, rel=0.01)


def test_a_candidate_refused_in_two_rounds_is_named_once_with_its_lowest_error():
    """Seen in benchmarks/real_data.py: "freeing d7, d7 would lower …" — a candidate is
    tried again in every round of the greedy choice, and was named once per round."""
    c = Choice(
        ident=None,  # type: ignore[arg-type]  # not read by tempting
        freed=("alpha5",),
        rule_mm=4.0,
        chosen_mm=3.0,
        tried=(("d7", 2.6, False), ("alpha5", 3.0, True), ("d7", 2.5, False), ("a7", 3.5, False)),
    )
    assert c.tempting == (("d7", 2.5),)
