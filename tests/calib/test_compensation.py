"""Compensated targets on a perturbed robot: the joints put the calibrated model's target
on the point, with the orientation asked for or near the seed when none is."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.calib.compensation import compensate
from cellcal.calib.geometry import so3_log
from cellcal.calib.kinematics import flange_transforms, target_kinematics
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import perturbed_model, random_joints

TOOL = np.array([20.0, -30.0, 120.0])


@pytest.mark.parametrize("name", ["kuka-kr5-arc", "ur10e"])
def test_the_joints_reach_the_points_with_the_true_model(name):
    nominal = load_model(name).model
    rng = np.random.default_rng(3)
    true = perturbed_model(nominal, rng)
    q_today = random_joints(nominal, rng, 12, span=0.5)
    # The points the program means: where the nominal model says it goes today.
    p = target_kinematics(nominal, q_today, TOOL, jacobian=False).p
    R = flange_transforms(nominal, q_today)[:, :3, :3]

    free = compensate(true, TOOL, nominal, p, None, q_today)
    assert free.ok.all(), free.why_not
    reached = target_kinematics(true, free.q, TOOL, jacobian=False).p
    assert np.abs(reached - p).max() < 1e-6
    # Least motion from the seed: a small change of today's joints.
    assert np.degrees(np.abs(free.q - q_today)).max() < 1.0
    # Without compensation the true robot misses by the injected errors' effect.
    today = target_kinematics(true, q_today, TOOL, jacobian=False).p
    assert np.linalg.norm(today - p, axis=1).mean() > 0.2

    posed = compensate(true, TOOL, nominal, p, R, q_today)
    assert posed.ok.all()
    assert np.abs(target_kinematics(true, posed.q, TOOL, jacobian=False).p - p).max() < 1e-6
    R_true = flange_transforms(true, posed.q)[:, :3, :3]
    turn = [np.linalg.norm(so3_log(a.T @ b)) for a, b in zip(R, R_true, strict=True)]
    assert max(turn) < 1e-9
    # The nominal model at the compensated joints is off by about what the robot was.
    assert posed.correction_mm.mean() == pytest.approx(
        np.linalg.norm(today - p, axis=1).mean(), rel=0.5
    )
    np.testing.assert_allclose(posed.T_base_flange_nominal, flange_transforms(nominal, posed.q))


def test_a_point_out_of_reach_is_named_not_returned():
    nominal = load_model("kuka-kr5-arc").model
    p = np.array([[600.0, 0.0, 800.0], [5000.0, 0.0, 800.0]])
    out = compensate(nominal, TOOL, nominal, p, None, np.zeros(6))
    assert out.ok.tolist() == [True, False]
    assert out.why_not[0] == ""
    assert "did not reach" in out.why_not[1] or "limits" in out.why_not[1]
