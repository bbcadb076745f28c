"""URDF out and in: what `cellcal export urdf` writes, Pinocchio (not cellcal) loads and
predicts the same target positions as `cellcal predict`; a URDF read back, and a public
UR5 URDF we did not write, give a model that predicts what Pinocchio predicts from the
file."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import model_from_dict, model_to_dict
from cellcal.files.models import load_model
from cellcal.files.urdf import model_from_urdf, to_urdf
from cellcal.mocks.robot_truth import perturbed_model, random_joints
from tests.calib.simulated import well_spread
from tests.cli.test_calibrate_cli import write_measurements
from tests.inprocess import cellcal
from tests.lazy import pinocchio as pin

ROOT = Path(__file__).parent
UR5 = ROOT / "data" / "urdf" / "ur5_robot.urdf"
TOOL = np.array([20.0, -30.0, 120.0])


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return cellcal(*args)


def _pinocchio(urdf: str, q: np.ndarray, frame: str, relative_to: str | None = None) -> np.ndarray:
    """Positions of ``frame`` (mm) by Pinocchio, in the root or in ``relative_to``."""
    pm = pin.buildModelFromXML(urdf)
    d = pm.createData()
    out = []
    for row in q:
        pin.framesForwardKinematics(pm, d, row)
        place = d.oMf[pm.getFrameId(frame)]
        if relative_to is not None:
            place = d.oMf[pm.getFrameId(relative_to)].actInv(place)
        out.append(np.array(place.translation) * 1000.0)
    return np.array(out)


def _predict(tmp_path: Path, model: str, q: np.ndarray) -> np.ndarray:
    """``cellcal predict`` (mm) for readings in rad."""
    joints = tmp_path / "joints.csv"
    joints.write_text(
        "q1,q2,q3,q4,q5,q6\n"
        + "".join(",".join(repr(float(v)) for v in np.degrees(r)) + "\n" for r in q)
    )
    run = _cli("predict", "--model", model, "--joints", str(joints))
    assert run.returncode == 0, run.stderr
    return np.loadtxt(run.stdout.splitlines()[1:], delimiter=",")[:, 6:9]


@pytest.mark.parametrize("name", ["kuka-kr5-arc", "ur5e", "ur10e"])
def test_exported_models_predict_what_cellcal_predicts(name, tmp_path):
    rng = np.random.default_rng(4)
    nominal = load_model(name).model
    q = random_joints(nominal, rng, 50)
    # The nominal model through the command, with its [tool] offset.
    out = tmp_path / "m.urdf"
    run = _cli("export", "urdf", "--model", name, "--out", str(out))
    assert run.returncode == 0, run.stderr
    urdf = out.read_text()
    ours = target_kinematics(nominal, q, nominal.target_offset, jacobian=False).p
    assert np.abs(_pinocchio(urdf, q, "target") - ours).max() < 1e-6
    # A perturbed one (β on the parallel rows, every angle off its round value).
    model = perturbed_model(nominal, rng)
    urdf = to_urdf(model, TOOL)
    ours = target_kinematics(model, q, TOOL, jacobian=False).p
    assert np.abs(_pinocchio(urdf, q, "target") - ours).max() < 1e-6


def test_a_calibrated_model_keeps_its_sensor_frame(tmp_path):
    d = well_spread("kuka-kr5-arc")
    data = write_measurements(tmp_path / "m.csv", d.q, d.m)
    model = tmp_path / "robot.toml"
    run = _cli("calibrate", "--model", "kuka-kr5-arc", "--data", str(data), "--out", str(model))
    assert run.returncode == 0, run.stderr
    out = tmp_path / "robot.urdf"
    run = _cli("export", "urdf", "--model", str(model), "--out", str(out), "--json")
    assert run.returncode == 0, run.stderr
    assert '"sensor"' in run.stdout
    q = d.q_val[:50]
    by_pinocchio = _pinocchio(out.read_text(), q, "target", relative_to="sensor")
    deviation = np.abs(by_pinocchio - _predict(tmp_path, str(model), q)).max()
    assert deviation < 1e-6 + 5e-7  # predict prints six decimals


def test_mdh_and_a_reversed_axis_and_a_coupling(tmp_path):
    doc = model_to_dict(load_model("kuka-kr5-arc").model)
    # The same robot in Craig's convention is not needed: any MDH table will do.
    doc["convention"] = "mdh"
    doc["joint"][2]["scale"] = -1.0
    model = model_from_dict(doc, "mdh-test")
    q = random_joints(model, np.random.default_rng(5), 50)
    ours = target_kinematics(model, q, TOOL, jacobian=False).p
    urdf = to_urdf(model, TOOL)
    assert 'xyz="0 0 -1"' in urdf
    assert np.abs(_pinocchio(urdf, q, "target") - ours).max() < 1e-6
    doc["joint"][2]["scale"] = 1.0
    doc["joint"][2]["couple"] = {"joint": 2, "factor": 1.0}
    coupled = tmp_path / "coupled.toml"
    import tomli_w

    coupled.write_text(tomli_w.dumps(doc))
    run = _cli("export", "urdf", "--model", str(coupled), "--out", str(tmp_path / "c.urdf"))
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "joint 3" in run.stderr and "URDF" in run.stderr
    assert not (tmp_path / "c.urdf").exists()


@pytest.mark.parametrize("name", ["kuka-kr5-arc", "ur10e"])
def test_a_urdf_read_back_is_the_same_robot(name, tmp_path):
    rng = np.random.default_rng(6)
    model = perturbed_model(load_model(name).model, rng)
    path = tmp_path / "r.urdf"
    path.write_text(to_urdf(model, np.zeros(3)))
    said: list[str] = []
    back = model_from_urdf(path, warn=said.append)
    assert back.convention == "mdh" and back.dof == 6
    # Its last DH row is perturbed too (a, α): a flange frame off joint 6's axis, which
    # a modified-DH table cannot end on, said in one line (tests/test_urdf_flange.py).
    assert len(said) == 1 and "target_offset_mm" in said[0]
    q = random_joints(model, rng, 50)
    flange = target_kinematics(model, q, np.zeros(3), jacobian=False).p
    assert (
        np.abs(target_kinematics(back, q, back.target_offset, jacobian=False).p - flange).max()
        < 1e-6
    )


def test_a_public_ur5_urdf(tmp_path):
    """The UR5 of ros-industrial's ur_description (via Gepetto's example-robot-data)."""
    model = load_model(str(UR5)).model
    q = random_joints(model, np.random.default_rng(7), 50)
    ours = target_kinematics(model, q, model.target_offset, jacobian=False).p
    theirs = _pinocchio(UR5.read_text(), q, "tool0")
    assert np.abs(ours - theirs).max() < 1e-6
    # Its derived table carries UR5's published DH lengths (mm), signs aside.
    lengths = sorted(round(abs(v), 6) for j in model.joints for v in (j.a, j.d) if abs(v) > 1e-9)
    assert lengths == sorted([89.159, 425.0, 392.25, 109.15, 94.65, 82.3])
    assert all(abs(math.degrees(j.alpha)) % 90 < 1e-6 for j in model.joints)
    assert all(j.beta == 0 for j in model.joints)
    # `cellcal predict` reads it too.
    np.testing.assert_allclose(_predict(tmp_path, str(UR5), q[:5]), theirs[:5], atol=1e-6)


def test_urdfs_cellcal_cannot_use_are_refused_in_one_line(tmp_path):
    cases = {
        "not xml": "this is not a URDF",
        "prismatic": (
            '<robot name="p"><link name="a"/><link name="b"/>'
            '<joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>'
            '<axis xyz="1 0 0"/><limit lower="0" upper="1" effort="1" velocity="1"/></joint>'
            "</robot>"
        ),
    }
    for what, text in cases.items():
        path = tmp_path / f"{what.replace(' ', '-')}.urdf"
        path.write_text(text)
        for args in (
            ["export", "urdf", "--model", str(path), "--out", str(tmp_path / "o.urdf")],
            ["predict", "--model", str(path), "--joints", str(path)],
        ):
            run = _cli(*args)
            assert run.returncode == 2, (what, run.stderr)
            assert run.stderr.count("\n") == 1 and str(path) in run.stderr, run.stderr
    run = _cli("export", "urdf", "--model", str(tmp_path / "missing.urdf"), "--out", "x.urdf")
    assert run.returncode == 2 and "missing.urdf" in run.stderr
    with pytest.raises(Exception, match=r"revolute"):
        model_from_urdf(tmp_path / "prismatic.urdf")


def test_a_urdfs_inertials_are_its_mass_model_and_give_pinocchios_gravity_torques():
    """The mass model read from ros-industrial's UR5 gives, through cellcal's own
    torques (the compliance term's regressor), what Pinocchio's computeGeneralizedGravity
    gives for the file, at random readings."""
    from cellcal.calib.error_terms import joint_torques
    from cellcal.calib.kinematics import chain_frames

    path = Path(__file__).parent / "data" / "urdf" / "ur5_robot.urdf"
    model = load_model(str(path)).model
    mass = model.mass_model
    assert mass is not None
    assert np.allclose(mass.mass_kg, [3.7, 8.393, 2.275, 1.219, 1.219, 0.1879])
    pm = pin.buildModelFromUrdf(str(path))
    data = pm.createData()
    rng = np.random.default_rng(4)
    q = rng.uniform(-np.pi, np.pi, (8, model.dof))
    ours = joint_torques(chain_frames(model, q), mass, np.zeros(len(q))) * 1000.0  # N·m
    ours *= 9.81 / 9.80665  # the file's gravity is Pinocchio's 9.81
    theirs = np.array([pin.computeGeneralizedGravity(pm, data, row) for row in q])
    assert np.allclose(ours, -theirs, atol=1e-9 * np.abs(theirs).max())
