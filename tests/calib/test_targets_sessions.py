"""Several targets, several sensor set-ups (sessions), 6-DOF measurements, and joint
readings that are not the joint angles (reversed axes, FANUC's J2/J3 coupling)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cellcal.calib.error_model import Groups, State, predict, predict_orientation
from cellcal.calib.geometry import so3_exp
from cellcal.calib.identification import calibrate
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import ModelError, model_from_dict, model_to_dict
from cellcal.calib.validation import cross_validate
from cellcal.errors import AcceptanceError, DegenerateGeometryError
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import random_cell, random_joints
from tests.lazy import Rotation

NOISE = 0.01  # mm
SMRS = np.array([[25.0, -40.0, 130.0], [-60.0, 35.0, 110.0], [40.0, 70.0, 95.0]])


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def _frame(rng):
    T = np.eye(4)
    T[:3, :3] = so3_exp(rng.normal(size=3))
    T[:3, 3] = rng.normal(size=3) * 1500.0
    return T


def _truth(groups, cell, target_offsets, frames):
    return State(cell.model, target_offsets, frames[:, :3, :3], frames[:, :3, 3], np.zeros(3))


def test_three_targets_each_get_their_own_offset():
    nominal = load_model("ur10e").model
    rng = np.random.default_rng(3)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, 90)
    labels = [("A", "B", "C")[k % 3] for k in range(len(q))]
    g = Groups.of(len(q), labels)
    truth = _truth(g, cell, SMRS, cell.T_sensor_base[None])
    m = predict(truth, q, g) + rng.normal(0, NOISE, (len(q), 3))
    res = calibrate(nominal, q, m, groups=g)
    assert res.targets == ("A", "B", "C")
    assert res.target_offsets is not None and res.target_offsets_std is not None

    # The targets' distances from each other are found; together they carry the last
    # row's errors (a rigid motion of the flange frame: 0.3 mm, 0.03° at most).
    def distances(t):
        return np.linalg.norm(t[:, None] - t[None], axis=2)

    assert (
        np.abs(distances(res.target_offsets) - distances(SMRS)).max()
        < 5 * res.target_offsets_std.max()
    )
    assert np.abs(res.target_offsets - SMRS).max() < 1.0
    assert res.rms_after < 2 * NOISE
    names = {p.name for p in res.parameters}
    assert {"target_offset_x:A", "target_offset_z:C"} <= names and "target_offset_x" not in names
    # One kinematic model for all three: held-out points of target B are predicted.
    q_val = random_joints(nominal, rng, 30)
    gb = Groups.of(30, ["B"] * 30)
    gb = Groups(gb.target + 1, gb.session, g.targets, g.sessions)
    assert _rms(res.predict(q_val, gb) - predict(truth, q_val, gb)) < 3 * NOISE


def test_each_session_gets_its_own_sensor_frame():
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(5)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, 120)
    sessions = ["monday" if k < 60 else "tuesday" for k in range(len(q))]
    g = Groups.of(len(q), None, sessions)
    frames = np.stack([_frame(rng), _frame(rng)])
    truth = _truth(g, cell, cell.target_offset, frames)
    m = predict(truth, q, g) + rng.normal(0, NOISE, (len(q), 3))
    res = calibrate(nominal, q, m, groups=g)
    assert res.sessions == ("monday", "tuesday")
    assert res.frames is not None
    for k in range(2):
        assert np.abs(res.frames[k][:3, 3] - frames[k][:3, 3]).max() < 0.5
        angle = Rotation.from_matrix(res.frames[k][:3, :3] @ frames[k][:3, :3].T).magnitude()
        assert math.degrees(angle) < 0.01
    assert res.rms_after < 2 * NOISE
    # The same data as one session cannot be explained: the two frames differ by metres.
    with pytest.raises(AcceptanceError):
        calibrate(nominal, q, m)
    # k-fold validation keeps the sessions apart.
    v = cross_validate(nominal, q, m, groups=g, folds=4)
    assert v.after.rms < 3 * NOISE


def test_a_session_of_two_points_is_refused():
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(6)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, 40)
    g = Groups.of(40, None, ["a"] * 38 + ["b"] * 2)
    with pytest.raises(DegenerateGeometryError, match="session 'b' has 2"):
        calibrate(nominal, q, cell.positions(q), groups=g)


def test_orientations_are_fitted_and_recover_the_target_orientation():
    nominal = load_model("ur10e").model
    rng = np.random.default_rng(8)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, 40)
    R_ft = so3_exp(np.radians([10.0, -20.0, 35.0]))
    k = target_kinematics(cell.model, q, cell.target_offset, jacobian=False)
    R_it = cell.T_sensor_base[:3, :3] @ k.R_flange @ R_ft
    noise_rad = math.radians(0.005)
    R_meas = np.stack([so3_exp(rng.normal(0, noise_rad, 3)) for _ in q]) @ R_it
    m = cell.positions(q) + rng.normal(0, NOISE, (len(q), 3))
    res6 = calibrate(nominal, q, m, orientations=R_meas)
    res3 = calibrate(nominal, q, m)
    assert res6.target_rotations is not None and res6.orientation_residuals is not None
    # The target's orientation on the flange (up to the last row's 0.03° errors)...
    err = Rotation.from_matrix(res6.target_rotations[0] @ R_ft.T).magnitude()
    assert math.degrees(err) < 0.1
    # ...and the orientation at held-out poses, to the noise.
    q_ho = random_joints(nominal, rng, 30)
    k_ho = target_kinematics(cell.model, q_ho, cell.target_offset, jacobian=False)
    R_true = cell.T_sensor_base[:3, :3] @ k_ho.R_flange @ R_ft
    R_pred = predict_orientation(res6.state, q_ho)
    held = Rotation.from_matrix(R_pred @ np.swapaxes(R_true, 1, 2)).magnitude()
    assert math.degrees(float(np.sqrt(np.mean(held**2)))) < 3 * math.degrees(noise_rad)
    rms_deg = math.degrees(float(np.sqrt(np.mean(np.sum(res6.orientation_residuals**2, 1)))))
    assert rms_deg < 3 * math.degrees(noise_rad) * math.sqrt(3)
    # Orientations add information: the kinematic parameters are known better.
    std6 = {p.name: p.std for p in res6.parameters if p.identified}
    std3 = {p.name: p.std for p in res3.parameters if p.identified}
    common = [n for n in std3 if n in std6 and not n.startswith("target_")]
    assert np.median([std6[n] / std3[n] for n in common]) < 0.9
    q_val = random_joints(nominal, rng, 30)
    assert _rms(res6.predict(q_val) - cell.positions(q_val)) < 3 * NOISE


def test_orientations_that_are_not_rotations_are_refused():
    nominal = load_model("ur10e").model
    q = random_joints(nominal, np.random.default_rng(1), 20)
    bad = np.tile(np.diag([1.0, 1.0, -1.0]), (20, 1, 1))
    with pytest.raises(Exception, match="not a rotation"):
        calibrate(nominal, q, np.zeros((20, 3)) + q[:, :3] * 100, orientations=bad)


# --------------------------------------------------------------------------- scale, couple


def _fanuc_like():
    """KR 5 arc geometry with FANUC's conventions: J2 reversed, J3 reading coupled to J2."""
    base = model_to_dict(load_model("kuka-kr5-arc").model)
    joints = [dict(j) for j in base["joint"]]  # type: ignore[union-attr]
    joints[1]["scale"] = -1.0
    joints[2]["couple"] = {"joint": 2, "factor": 1.0}
    return model_from_dict({**base, "joint": joints})


def test_scale_and_couple_map_readings_to_joint_angles():
    coupled = _fanuc_like()
    plain = load_model("kuka-kr5-arc").model
    q = random_joints(plain, np.random.default_rng(2), 10)
    angles = q.copy()
    angles[:, 1] = -q[:, 1]
    angles[:, 2] = q[:, 2] + q[:, 1]
    p1 = target_kinematics(coupled, q, plain.target_offset, jacobian=False).p
    p2 = target_kinematics(plain, angles, plain.target_offset, jacobian=False).p
    np.testing.assert_allclose(p1, p2, atol=1e-9)
    # Written and read back unchanged.
    again = model_from_dict(model_to_dict(coupled))
    assert again.joints[1].scale == -1.0
    assert (again.joints[2].couple_joint, again.joints[2].couple_factor) == (2, 1.0)
    # Inverse kinematics answers in readings.
    k = target_kinematics(coupled, q, plain.target_offset, jacobian=False)
    sol = solve(coupled, plain.target_offset, k.p, k.R_flange, q + 0.05)
    assert sol.ok.all()
    np.testing.assert_allclose(
        target_kinematics(coupled, sol.q, plain.target_offset, jacobian=False).p, k.p, atol=1e-6
    )


def test_calibration_with_a_coupled_model_recovers_the_robot():
    coupled = _fanuc_like()
    rng = np.random.default_rng(4)
    cell = random_cell(coupled, rng)
    q = random_joints(coupled, rng, 60)
    m = cell.positions(q) + rng.normal(0, NOISE, (len(q), 3))
    res = calibrate(coupled, q, m)
    q_val = random_joints(coupled, rng, 30)
    assert _rms(res.predict(q_val) - cell.positions(q_val)) < 3 * NOISE
    # The same data read without the coupling do not fit.
    plain = replace(
        coupled, joints=tuple(replace(j, scale=1.0, couple_joint=0) for j in coupled.joints)
    )
    with pytest.raises(AcceptanceError):
        calibrate(plain, q, m)


@pytest.mark.parametrize(
    ("joint", "message"),
    [
        ({"scale": 0.0}, "must not be 0"),
        ({"couple": {"joint": 9, "factor": 1.0}}, "joint number 1..6"),
        ({"couple": {"joint": 3, "factor": 1.0}}, "couple to itself"),
        ({"couple": {"joint": 2}}, "joint = J, factor = F"),
        ({"couple": 2}, "joint = J, factor = F"),
    ],
)
def test_bad_scale_or_couple_is_refused(joint, message):
    base = model_to_dict(load_model("kuka-kr5-arc").model)
    joints = [dict(j) for j in base["joint"]]  # type: ignore[union-attr]
    joints[2].update(joint)
    with pytest.raises(ModelError, match=message):
        model_from_dict({**base, "joint": joints})


def test_a_singular_reading_map_is_refused():
    base = model_to_dict(load_model("kuka-kr5-arc").model)
    joints = [dict(j) for j in base["joint"]]  # type: ignore[union-attr]
    joints[2]["scale"] = 1.0
    joints[2]["couple"] = {"joint": 2, "factor": 1.0}
    joints[1]["couple"] = {"joint": 3, "factor": 1.0}  # angle2 = q2 + q3 = angle3
    with pytest.raises(ModelError, match="singular"):
        model_from_dict({**base, "joint": joints})
