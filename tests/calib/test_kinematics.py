"""Forward kinematics and its Jacobian against Pinocchio and finite differences."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import ROW_PARAMS, flange_transforms, target_kinematics
from cellcal.calib.robot_model import model_from_dict
from cellcal.files.models import load_model
from tests.lazy import pinocchio as pin

TOOL = np.array([12.0, -34.0, 56.0])


def _mdh_model():
    rows = [
        {"a": 0.0, "alpha": 0.0, "d": 300.0, "theta": 0.0},
        {"a": 150.0, "alpha": -90.0, "d": 0.0, "theta": -90.0},
        {"a": 500.0, "alpha": 0.0, "d": 20.0, "theta": 0.0},
        {"a": 100.0, "alpha": -90.0, "d": 480.0, "theta": 0.0},
        {"a": 0.0, "alpha": 90.0, "d": 0.0, "theta": 0.0},
        {"a": 0.0, "alpha": -90.0, "d": 80.0, "theta": 0.0},
    ]
    for r in rows:
        r["beta"] = 0.05
    return model_from_dict({"name": "mdh-arm", "convention": "mdh", "joint": rows})


def _rot(axis, angle):
    return pin.utils.rotate(axis, angle)


def _pinocchio(model):
    """The same robot as a Pinocchio model of revolute-z joints with fixed placements."""
    pm = pin.Model()
    parent = 0
    pre = pin.SE3.Identity()  # fixed transform between the previous joint and this one
    for i, j in enumerate(model.joints):
        if model.convention == "dh":
            placement = pre * pin.SE3(_rot("z", j.theta), np.zeros(3))
            after = (
                pin.SE3(np.eye(3), np.array([j.a, 0.0, j.d]))
                * pin.SE3(_rot("x", j.alpha), np.zeros(3))
                * pin.SE3(_rot("y", j.beta), np.zeros(3))
            )
        else:
            before = (
                pin.SE3(_rot("x", j.alpha), np.zeros(3))
                * pin.SE3(_rot("y", j.beta), np.zeros(3))
                * pin.SE3(np.eye(3), np.array([j.a, 0.0, 0.0]))
            )
            placement = pre * before * pin.SE3(_rot("z", j.theta), np.zeros(3))
            after = pin.SE3(np.eye(3), np.array([0.0, 0.0, j.d]))
        parent = pm.addJoint(parent, pin.JointModelRZ(), placement, f"j{i + 1}")
        pre = after
    pm.addFrame(pin.Frame("flange", parent, 0, pre, pin.FrameType.OP_FRAME))
    return pm


MODELS = [
    load_model("kuka-kr5-arc").model,
    load_model("ur10e").model,
    _mdh_model(),
]


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
def test_positions_match_pinocchio(model):
    pm = _pinocchio(model)
    pd = pm.createData()
    fid = pm.getFrameId("flange")
    q = np.random.default_rng(0).uniform(-2.5, 2.5, (20, 6))
    k = target_kinematics(model, q, TOOL)
    T = flange_transforms(model, q)
    for i in range(len(q)):
        pin.framesForwardKinematics(pm, pd, q[i])
        M = pd.oMf[fid]
        np.testing.assert_allclose(M.translation + M.rotation @ TOOL, k.p[i], atol=1e-9)
        np.testing.assert_allclose(M.rotation, T[i, :3, :3], atol=1e-12)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
def test_jacobian_matches_finite_differences(model):
    q = np.random.default_rng(1).uniform(-2.0, 2.0, (7, 6))
    k = target_kinematics(model, q, TOOL)
    eps = 1e-6
    for i in range(model.dof):
        for kind_index, kind in enumerate(ROW_PARAMS):
            joints = list(model.joints)
            joints[i] = replace(joints[i], **{kind: getattr(joints[i], kind) + eps})
            hi = target_kinematics(model.with_joints(tuple(joints)), q, TOOL, jacobian=False).p
            joints[i] = replace(joints[i], **{kind: getattr(model.joints[i], kind) - eps})
            lo = target_kinematics(model.with_joints(tuple(joints)), q, TOOL, jacobian=False).p
            numeric = (hi - lo) / (2 * eps)
            np.testing.assert_allclose(
                k.J_rows[:, :, 5 * i + kind_index], numeric, atol=2e-5, err_msg=f"{kind}{i + 1}"
            )
    # ∂p/∂q is the θ column, and the joint axes are unit vectors.
    np.testing.assert_allclose(np.linalg.norm(k.axes, axis=1), 1.0, atol=1e-12)


def test_inverse_kinematics_round_trip():
    model = load_model("kuka-kr5-arc").model
    q_true = np.radians([[5, -35, 45, 10, -25, 15], [-10, -25, 35, -5, -30, 0]])
    k = target_kinematics(model, q_true, TOOL, jacobian=False)
    sol = solve(model, TOOL, k.p, k.R_flange, np.radians([0, -30, 40, 0, -20, 0]))
    assert sol.ok.all()
    k2 = target_kinematics(model, sol.q, TOOL, jacobian=False)
    np.testing.assert_allclose(k2.p, k.p, atol=1e-6)
    np.testing.assert_allclose(k2.R_flange, k.R_flange, atol=1e-9)


def test_inverse_kinematics_reports_unreachable():
    model = load_model("kuka-kr5-arc").model
    far = np.array([[5000.0, 0.0, 1000.0]])
    sol = solve(model, TOOL, far, np.eye(3), np.radians([0, -30, 40, 0, -20, 0]), max_iter=50)
    assert not sol.ok.any()
    assert sol.position_error[0] > 1000.0
