"""A check's limits, verdict and cause (``calib/drift.py``), on errors made from a known
change of a known robot: each cause is named with its size, the ones a check cannot
tell apart are named together, noise alone is no cause, and the limits come from the
model's uncertainty, its validation and the earlier checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.calib import drift
from cellcal.calib.error_model import parameter_specs
from cellcal.calib.geometry import so3_exp
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import TrueCell, changed_model, grown_model
from cellcal.simulation_config import SimulatedChange

NOMINAL = load_model("kuka-kr5-arc").model
OFFSET = np.array([25.0, -40.0, 130.0])
T = np.eye(4)
T[:3, :3] = so3_exp(np.radians([0.0, 0.0, 160.0]))
T[:3, 3] = [2800.0, -600.0, 300.0]
PIVOT = np.array([900.0, 100.0, 1000.0])
STATE = drift.model_state(NOMINAL, OFFSET, T, PIVOT)
NOISE_MM = 0.005


def _poses(n: int = 12, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    home = np.radians([0.0, -30.0, 40.0, 0.0, -20.0, 0.0])
    return home + np.radians(rng.uniform(-25, 25, (n, 6)))


def _errors(model, q, *, T_truth=T, offset=OFFSET, seed=2) -> np.ndarray:
    truth = TrueCell(model, offset, T_truth).positions(q)
    noise = np.random.default_rng(seed).normal(scale=NOISE_MM / math.sqrt(3), size=truth.shape)
    return drift.pose_errors(STATE, q, truth + noise)


def _diagnose(errors, q):
    return drift.diagnose(STATE, q, errors, NOISE_MM, 2 * NOISE_MM)


@pytest.mark.parametrize(
    ("change", "name", "key", "value"),
    [
        (SimulatedChange(joint_offset_deg=[0, 0.02, 0, 0, 0, 0]), "theta2", "theta2", 0.02),
        (SimulatedChange(joint_offset_deg=[0, 0, 0, 0, -0.03, 0]), "theta5", "theta5", -0.03),
        (SimulatedChange(link_mm={"a2": 0.1}), "a2", "a2", 0.1),
        (SimulatedChange(link_mm={"d4": -0.15}), "d4", "d4", -0.15),
    ],
)
def test_a_joint_offset_or_a_link_is_named_with_its_size(change, name, key, value):
    q = _poses()
    d = _diagnose(_errors(changed_model(NOMINAL, change), q), q)
    assert d.cause is not None and d.cause.name == name
    assert d.cause.values[key] == pytest.approx(value, rel=0.05)
    assert d.cause.explained > 0.99


def test_a_shifted_base_is_named_in_the_robot_base_axes():
    q = _poses()
    shift = np.array([0.2, -0.1, 0.05])
    moved = T.copy()
    moved[:3, 3] += T[:3, :3] @ shift  # the base (and the robot on it) moved
    d = _diagnose(_errors(NOMINAL, q, T_truth=moved), q)
    assert d.cause is not None and d.cause.name == "frame_shift"
    got = [d.cause.values[k] for k in ("x_mm", "y_mm", "z_mm")]
    np.testing.assert_allclose(got, shift, atol=0.005)
    assert "frame_move" not in [a.name for a in d.alternatives]  # says nothing more


def test_causes_a_check_cannot_tell_apart_are_named_together():
    q = _poses()
    joint1 = changed_model(NOMINAL, SimulatedChange(joint_offset_deg=[0.02, 0, 0, 0, 0, 0]))
    d = _diagnose(_errors(joint1, q), q)
    assert d.cause is not None and d.cause.name == "theta1"
    assert [a.name for a in d.alternatives] == ["frame_move"]  # the base turned about z
    assert d.sentence is not None and "cannot tell them apart" in d.sentence


def test_a_grown_arm_and_a_moved_target_are_named():
    q = _poses()
    reach = sum(abs(j.a) + abs(j.d) for j in NOMINAL.joints)
    d = _diagnose(_errors(grown_model(NOMINAL, 0.3), q), q)
    assert d.cause is not None and d.cause.name == "growth"
    assert d.cause.values["ppm"] == pytest.approx(0.3 / reach * 1e6, rel=0.05)
    d = _diagnose(_errors(NOMINAL, q, offset=OFFSET + np.array([0.1, 0.0, -0.1])), q)
    assert d.cause is not None and d.cause.name == "target"
    assert d.cause.values["x_mm"] == pytest.approx(0.1, abs=0.01)


def test_errors_no_single_cause_explains_are_no_cause():
    q = _poses()
    rng = np.random.default_rng(3)
    assert _diagnose(rng.normal(scale=0.1, size=(len(q), 3)), q).cause is None
    two = changed_model(NOMINAL, SimulatedChange(joint_offset_deg=[0, 0.02, 0, -0.03, 0, 0]))
    d = _diagnose(_errors(two, q), q)
    assert d.cause is None and d.sentence is None


def test_limits_are_the_largest_of_prediction_validation_and_earlier_checks():
    lim = drift.control_limits(0.006, None, [0.02, 0.02], 2.0, 3.0)
    assert lim.earlier_mm is None and lim.sigma_mm == 0.006  # two earlier checks: not yet
    assert (lim.warning_mm, lim.limit_mm) == pytest.approx((0.012, 0.018))
    lim = drift.control_limits(0.006, 0.008, [], 2.0, 3.0)
    assert lim.sigma_mm == 0.008
    lim = drift.control_limits(0.006, 0.008, [0.009, 0.012, 0.010], 2.0, 3.0)
    assert lim.earlier_mm == pytest.approx(math.sqrt((0.009**2 + 0.012**2 + 0.010**2) / 3))
    assert lim.sigma_mm == lim.earlier_mm and lim.n_earlier == 3


def test_the_verdict_is_on_the_rms_and_a_single_pose_is_a_warning():
    lim = drift.control_limits(0.01, None, [], 2.0, 3.0)
    assert drift.verdict([0.01] * 12, lim) == drift.OK
    assert drift.verdict([0.025] * 12, lim) == drift.WARNING
    assert drift.verdict([0.031] * 12, lim) == drift.RECALIBRATE
    assert drift.verdict([0.005] * 11 + [0.035], lim) == drift.WARNING


def test_the_predicted_rms_is_the_noise_and_the_covariance_propagated():
    q = _poses()
    specs = tuple(s for s in parameter_specs(NOMINAL) if s.name in ("theta2", "a3"))
    none = drift.ModelUncertainty(specs, np.zeros((2, 2)), PIVOT, NOISE_MM)
    assert drift.predicted_rms(STATE, q, none) == pytest.approx(NOISE_MM)
    # θ2 known to 0.01°: its effect at the poses, by finite differences
    cov = np.diag([math.radians(0.01) ** 2, 0.0])
    u = drift.ModelUncertainty(specs, cov, PIVOT, 0.0)
    turned = changed_model(NOMINAL, SimulatedChange(joint_offset_deg=[0, 0.01, 0, 0, 0, 0]))
    moved = TrueCell(turned, OFFSET, T).positions(q) - TrueCell(NOMINAL, OFFSET, T).positions(q)
    expected = math.sqrt(np.mean(np.sum(moved**2, axis=1)))
    assert drift.predicted_rms(STATE, q, u) == pytest.approx(expected, rel=1e-3)
