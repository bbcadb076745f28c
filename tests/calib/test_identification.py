"""Identification on simulated robots with known injected errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.calib.error_model import State, jacobian, parameter_specs, predict
from cellcal.calib.identifiability import analyse
from cellcal.calib.identification import calibrate, fit_frames
from cellcal.calib.validation import ErrorStats, cross_validate
from cellcal.errors import DegenerateGeometryError, InputError
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import measure, random_cell, random_joints
from tests.calib.simulated import NOISE_MM, paper_cube, well_spread


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


@pytest.mark.parametrize("robot", ["kuka-kr5-arc", "ur10e"])
def test_recovers_injected_errors_within_noise(robot):
    nominal = load_model(robot).model
    d = well_spread(robot)
    res = calibrate(nominal, d.q, d.m)
    held_out = _rms(res.predict(d.q_val) - d.m_val_true)
    base = fit_frames(nominal, d.q, d.m)
    before = _rms(predict(base, d.q_val) - d.m_val_true)
    assert held_out < 3 * NOISE_MM
    assert before / held_out > 10.0
    assert res.sigma0 == pytest.approx(NOISE_MM, rel=0.25)
    # θ1, d1 are absorbed by the sensor frame; the last row by the target offset.
    assert set(res.unidentifiable) == {"theta1", "d1", "theta6", "d6", "a6", "alpha6"}
    assert res.condition_number < 200
    # The parallel pair is described by β, and β is found.
    beta2 = next(p for p in res.parameters if p.name == "beta2")
    true_beta = math.degrees(d.cell.model.joints[1].beta)
    assert beta2.identified and beta2.value == pytest.approx(true_beta, abs=5 * beta2.std + 1e-3)


def test_noise_free_data_are_fitted_exactly():
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(11)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, 40)
    res = calibrate(nominal, q, cell.positions(q))
    q_val = random_joints(nominal, rng, 50)
    assert res.rms_after < 1e-7
    assert _rms(res.predict(q_val) - cell.positions(q_val)) < 1e-6
    assert res.rms_before > 0.05  # the nominal model, even with the best frames, is not


def test_reported_uncertainties_match_the_scatter():
    """Repeat the calibration on fresh noise: the spread of a parameter is its σ."""
    nominal = load_model("ur10e").model
    d = well_spread("ur10e")
    rng = np.random.default_rng(99)
    truth = d.cell.positions(d.q)
    values, stds = [], []
    for _ in range(40):
        res = calibrate(nominal, d.q, truth + rng.normal(0, NOISE_MM, truth.shape))
        pick = {p.name: p for p in res.parameters}
        values.append([pick[n].value for n in ("a2", "beta3", "alpha4", "target_offset_z")])
        stds.append([pick[n].std for n in ("a2", "beta3", "alpha4", "target_offset_z")])
    observed = np.std(values, axis=0, ddof=1)
    predicted = np.mean(stds, axis=0)
    np.testing.assert_allclose(observed, predicted, rtol=0.4)


def test_paper_ranks_with_the_base_fixed():
    """A rank of 24 is often assumed for the paper's 27 parameters on a KR 5 arc (base fixed);
    the identification Jacobian says 22: the target offset absorbs θ6, d6, a6, α6, and
    d2, d3 lie along parallel axes. UR10e (three parallel axes): 21."""
    expected = {"kuka-kr5-arc": 22, "ur10e": 21}
    for robot, rank in expected.items():
        nominal = load_model(robot).model
        q = random_joints(nominal, np.random.default_rng(0), 100)
        st = State(nominal, np.array([25.0, -40.0, 130.0]), np.eye(3), np.zeros(3), np.zeros(3))
        specs = parameter_specs(nominal, paper_parameters=True, frame=False)
        assert len(specs) == 27
        _, J = jacobian(st, q, specs)
        a = analyse(J.reshape(-1, len(specs)), specs)
        assert len(a.identified) == rank
        assert {"theta6", "d6", "a6", "alpha6"} <= set(a.unidentifiable_names)
        # With Hayati's β in place of d on the parallel rows, one more each.
        specs = parameter_specs(nominal, frame=False)
        _, J = jacobian(st, q, specs)
        assert len(analyse(J.reshape(-1, len(specs)), specs).identified) == 23


def test_paper_fixed_orientation_cube_is_ill_conditioned_but_still_helps():
    nominal = load_model("kuka-kr5-arc").model
    d = paper_cube(0.0)
    res = calibrate(nominal, d.q, d.m)
    assert res.condition_number > 1e3
    assert any("ill-conditioned" in w for w in res.warnings)
    # With one orientation the target offset cannot be told from the sensor's origin.
    assert {"target_offset_x", "target_offset_y", "target_offset_z"} <= set(res.unidentifiable)
    base = fit_frames(nominal, d.q, d.m)
    before = _rms(predict(base, d.q_val) - d.m_val_true)
    after = _rms(res.predict(d.q_val) - d.m_val_true)
    assert after < before / 5
    # Varying the wrist per point conditions it well and identifies the offset.
    v = paper_cube(30.0)
    res_v = calibrate(nominal, v.q, v.m)
    assert res_v.condition_number < res.condition_number / 5
    assert "target_offset_z" in res_v.identified


def test_weights_from_sigma_discount_poor_points():
    nominal = load_model("kuka-kr5-arc").model
    d = well_spread("kuka-kr5-arc")
    m = d.m.copy()
    sigma = np.full_like(m, NOISE_MM)
    m[:8] += np.random.default_rng(3).normal(0, 0.5, (8, 3))  # eight poor points ...
    sigma[:8] = 0.5  # ... that say so
    plain = _rms(calibrate(nominal, d.q, m).predict(d.q_val) - d.m_val_true)
    weighted = calibrate(nominal, d.q, m, sigma)
    assert weighted.weighted
    assert _rms(weighted.predict(d.q_val) - d.m_val_true) < plain / 3
    assert weighted.sigma0 == pytest.approx(1.0, rel=0.3)  # dimensionless with 1/σ weights


def test_robust_loss_resists_gross_errors():
    nominal = load_model("ur10e").model
    d = well_spread("ur10e")
    m = d.m.copy()
    m[[3, 17, 41]] += [[3.0, 0, 0], [0, -4.0, 0], [0, 0, 5.0]]
    plain = _rms(calibrate(nominal, d.q, m).predict(d.q_val) - d.m_val_true)
    robust = _rms(calibrate(nominal, d.q, m, robust="soft_l1").predict(d.q_val) - d.m_val_true)
    assert robust < plain / 3
    assert robust < 3 * NOISE_MM


def test_cross_validation_and_stats():
    nominal = load_model("kuka-kr5-arc").model
    d = well_spread("kuka-kr5-arc")
    v = cross_validate(nominal, d.q, d.m, folds=4)
    assert v.method == "k-fold k=4"
    assert v.after.n == len(d.q)
    assert v.after.rms < 2.5 * NOISE_MM * math.sqrt(3)
    assert v.improvement > 10
    s = ErrorStats.of(np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]))
    assert (s.n, s.mean, s.max) == (2, 3.0, 5.0)
    assert s.rms == pytest.approx(math.sqrt(13.0))
    with pytest.raises(InputError, match="folds"):
        cross_validate(nominal, d.q, d.m, folds=1)


def test_bad_inputs():
    nominal = load_model("kuka-kr5-arc").model
    d = well_spread("kuka-kr5-arc")
    q = d.q.copy()
    q[5, 2] = math.radians(170.0)  # A3 max is 158°
    with pytest.raises(InputError, match=r"row 6: joint 3 reads 170\.000°"):
        calibrate(nominal, q, d.m)
    m = d.m.copy()
    m[9, 1] = np.nan
    with pytest.raises(InputError, match="measurements: row 10 is not finite"):
        calibrate(nominal, d.q, m)
    with pytest.raises(InputError, match="expected N×6"):
        calibrate(nominal, d.q[:, :5], d.m)
    with pytest.raises(InputError, match="80×3"):
        calibrate(nominal, d.q, d.m[:, :2])
    with pytest.raises(InputError, match=r"measure at least \d+ poses"):
        calibrate(nominal, d.q[:8], d.m[:8])
    with pytest.raises(InputError, match="robust"):
        calibrate(nominal, d.q, d.m, robust="magic")
    with pytest.raises(InputError, match="sx, sy, sz"):
        calibrate(nominal, d.q, d.m, np.zeros_like(d.m))


def test_degenerate_measurements():
    nominal = load_model("kuka-kr5-arc").model
    q = random_joints(nominal, np.random.default_rng(4), 30)
    line = np.outer(np.arange(30.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateGeometryError):
        calibrate(nominal, q, line)


def test_measure_is_reproducible():
    nominal = load_model("ur5e").model
    a = random_cell(nominal, np.random.default_rng(7))
    b = random_cell(nominal, np.random.default_rng(7))
    assert a.model == b.model
    q = random_joints(nominal, np.random.default_rng(8), 5)
    np.testing.assert_array_equal(
        measure(a, q, np.random.default_rng(9), 0.01), measure(b, q, np.random.default_rng(9), 0.01)
    )
