"""A URDF read as a model keeps the file's flange frame, position and orientation: a
model exported and read back has the flange frame it had (so a cell's target_offset_mm
names the same point and `cellcal plan` plans the same poses), a public URDF's tool0 is
the model's flange frame, and an end frame a DH model cannot end on is said in one
warning line."""

from __future__ import annotations

import json
import math
import re
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from cellcal.calib.geometry import so3_log
from cellcal.calib.kinematics import flange_transforms, target_kinematics
from cellcal.calib.robot_model import RobotModel, model_from_dict, model_to_dict
from cellcal.files.models import builtin_names, load_model
from cellcal.files.urdf import model_from_urdf, to_urdf
from cellcal.mocks.robot_truth import perturbed_model, random_joints
from tests.calib.simulated import well_spread
from tests.cli.test_calibrate_cli import write_measurements
from tests.inprocess import cellcal
from tests.lazy import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
UR5 = ROOT / "tests" / "data" / "urdf" / "ur5_robot.urdf"
CELLS = {
    "kuka-kr5-arc": ROOT / "config" / "mock-cell-tracker.toml",
    "ur10e": ROOT / "config" / "mock-cell-ur10e.toml",
}
#: the mock cells' target offset on the flange (mm)
OFFSET = np.array([25.0, -40.0, 130.0])
#: the tool0 joint of ros-industrial's UR5 (wrist_3_link → tool0)
TOOL0_ORIGIN = '<origin rpy="-1.57079632679 0 0" xyz="0 0.0823 0"/>'


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return cellcal(*args)


def _read(path: Path) -> tuple[RobotModel, list[str]]:
    said: list[str] = []
    return model_from_urdf(path, warn=said.append), said


def _assert_same_flange(a: RobotModel, b: RobotModel, q: np.ndarray) -> None:
    Ta, Tb = flange_transforms(a, q), flange_transforms(b, q)
    assert np.abs(Ta[:, :3, 3] - Tb[:, :3, 3]).max() < 1e-9  # mm
    assert np.abs(Ta[:, :3, :3] - Tb[:, :3, :3]).max() < 1e-9
    pa = target_kinematics(a, q, OFFSET, jacobian=False).p
    pb = target_kinematics(b, q, OFFSET, jacobian=False).p
    assert np.abs(pa - pb).max() < 1e-9


def _by_pinocchio(urdf: str, q: np.ndarray, frame: str) -> np.ndarray:
    """T_root_frame (N×4×4, mm) by Pinocchio's own frame placements."""
    pm = pin.buildModelFromXML(urdf)
    d = pm.createData()
    fid = pm.getFrameId(frame)
    out = np.tile(np.eye(4), (len(q), 1, 1))
    for k, row in enumerate(q):
        pin.framesForwardKinematics(pm, d, row)
        out[k, :3, :3] = d.oMf[fid].rotation
        out[k, :3, 3] = d.oMf[fid].translation * 1000.0
    return out


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A calibrated KR 5 arc (its last row's α is 180°: the flange's z against joint 6's
    axis) written by `cellcal calibrate`."""
    folder = tmp_path_factory.mktemp("calibrated")
    d = well_spread("kuka-kr5-arc")
    data = write_measurements(folder / "m.csv", d.q, d.m)
    out = folder / "robot.toml"
    run = _cli("calibrate", "--model", "kuka-kr5-arc", "--data", str(data), "--out", str(out))
    assert run.returncode == 0, run.stderr
    return out


@pytest.mark.parametrize("name", builtin_names())
def test_a_builtin_model_read_back_has_its_flange_frame(name, tmp_path):
    model = load_model(name).model
    path = tmp_path / f"{name}.urdf"
    path.write_text(to_urdf(model, OFFSET))
    back, said = _read(path)
    assert said == []
    _assert_same_flange(model, back, random_joints(model, np.random.default_rng(11), 50))


@pytest.mark.parametrize("last_scale", [1.0, -1.0])
def test_any_modified_dh_table_read_back_has_its_flange_frame(last_scale, tmp_path):
    """A modified-DH table always ends on its last axis: perturbed (every angle off its
    round value, β on parallel rows, axes 5 and 6 anti-parallel), with reversed axes."""
    doc = model_to_dict(load_model("kuka-kr5-arc").model)
    doc["convention"] = "mdh"
    doc["joint"][2]["scale"] = -1.0
    doc["joint"][5]["scale"] = last_scale
    nominal = model_from_dict(doc, "mdh-test")
    rng = np.random.default_rng(15)
    model = perturbed_model(nominal, rng)
    path = tmp_path / "mdh.urdf"
    path.write_text(to_urdf(model, OFFSET))
    back, said = _read(path)
    assert said == []
    _assert_same_flange(model, back, random_joints(model, rng, 50))


def test_a_calibrated_model_read_back_has_its_flange_frame(calibrated, tmp_path):
    out = tmp_path / "robot.urdf"
    run = _cli("export", "urdf", "--model", str(calibrated), "--out", str(out))
    assert run.returncode == 0, run.stderr
    model = load_model(str(calibrated)).model
    back, said = _read(out)
    assert said == []
    # KR 5's flange z points against joint 6's axis: the read model's last frame does too.
    assert back.joints[-1].scale == -1.0
    _assert_same_flange(model, back, random_joints(model, np.random.default_rng(12), 50))


def _plan(config: Path, model: str, tmp_path: Path, tag: str) -> dict[str, object]:
    doc = tomllib.loads(config.read_text())
    doc["robot"]["model"] = model
    path = tmp_path / f"cell-{tag}.toml"
    path.write_text(tomli_w.dumps(doc))
    run = _cli("plan", "--config", str(path), "--json")
    assert run.returncode == 0, run.stderr
    assert "warning" not in run.stderr, run.stderr
    out: dict[str, object] = json.loads(run.stdout)
    return out


def _assert_same_plan(a: dict, b: dict) -> None:
    assert (a["n_poses"], a["n_unreachable"], a["regions"]) == (
        b["n_poses"],
        b["n_unreachable"],
        b["regions"],
    )
    assert len(a["poses"]) == len(b["poses"])
    for pa, pb in zip(a["poses"], b["poses"], strict=True):
        for key in ("idx", "role", "region", "reachable", "reason"):
            assert pa.get(key) == pb.get(key)
        np.testing.assert_allclose(pa["target_mm"], pb["target_mm"], atol=2e-6)
        if pa["reachable"]:
            np.testing.assert_allclose(pa["q_deg"], pb["q_deg"], atol=2e-6)


@pytest.mark.parametrize("name", sorted(CELLS))
def test_a_cell_plans_the_same_poses_with_the_urdf_of_its_model(name, tmp_path):
    urdf = tmp_path / f"{name}.urdf"
    run = _cli("export", "urdf", "--model", name, "--out", str(urdf))
    assert run.returncode == 0, run.stderr
    by_name = _plan(CELLS[name], name, tmp_path, "name")
    by_urdf = _plan(CELLS[name], str(urdf), tmp_path, "urdf")
    assert by_name["n_poses"] > 100
    _assert_same_plan(by_name, by_urdf)


def test_a_cell_plans_the_same_poses_with_the_urdf_of_a_calibrated_model(calibrated, tmp_path):
    urdf = tmp_path / "robot.urdf"
    run = _cli("export", "urdf", "--model", str(calibrated), "--out", str(urdf))
    assert run.returncode == 0, run.stderr
    cell = CELLS["kuka-kr5-arc"]
    _assert_same_plan(
        _plan(cell, str(calibrated), tmp_path, "toml"), _plan(cell, str(urdf), tmp_path, "urdf")
    )


def _ur5(tmp_path: Path, origin: str) -> Path:
    text = UR5.read_text()
    assert text.count(TOOL0_ORIGIN) == 1
    path = tmp_path / "ur5.urdf"
    path.write_text(text.replace(TOOL0_ORIGIN, origin))
    return path


@pytest.mark.parametrize(
    ("origin", "scale"),
    [
        (TOOL0_ORIGIN, 1.0),  # the file as published: z along wrist 3's axis
        ('<origin rpy="-1.57079632679 0.7 0" xyz="0 0.0823 0"/>', 1.0),  # turned about it
        ('<origin rpy="1.57079632679 0.3 0" xyz="0 0.15 0"/>', -1.0),  # z against it
    ],
    ids=["as-published", "turned-about-the-axis", "z-against-the-axis"],
)
def test_a_public_urdfs_tool0_is_the_models_flange_frame(origin, scale, tmp_path):
    """ros-industrial's UR5 (tool0: z along wrist 3's axis, x turned from the DH frame's
    x) and two variants of its tool0: the model's flange frame is Pinocchio's tool0."""
    path = _ur5(tmp_path, origin)
    model, said = _read(path)
    assert said == []
    assert model.joints[-1].scale == scale
    q = random_joints(model, np.random.default_rng(13), 50)
    theirs = _by_pinocchio(path.read_text(), q, "tool0")
    ours = flange_transforms(model, q)
    assert np.abs(ours[:, :3, 3] - theirs[:, :3, 3]).max() < 1e-9
    assert np.abs(ours[:, :3, :3] - theirs[:, :3, :3]).max() < 1e-9
    assert np.abs(np.asarray(model.target_offset_xyz)).max() < 1e-9


def test_a_tool0_a_dh_model_cannot_end_on_is_said_in_one_line(tmp_path):
    """tool0 tilted 0.1 rad off wrist 3's axis and 20 mm off it: the model's flange frame
    is the nearest one on the axis, and one warning line gives the turn and the offset
    that take it to tool0."""
    path = _ur5(tmp_path, '<origin rpy="-1.47079632679 0 0" xyz="0.02 0.0823 0"/>')
    model, said = _read(path)
    assert len(said) == 1
    line = said[0]
    assert "'tool0'" in line and "target_offset_mm" in line, line
    assert "5.72958°" in line and "20 mm off joint 6's axis" in line, line
    q = random_joints(model, np.random.default_rng(14), 50)
    theirs = _by_pinocchio(path.read_text(), q, "tool0")
    ours = flange_transforms(model, q)
    # tool0's origin is the model's [tool] offset; its axes a fixed turn of the flange's.
    p = target_kinematics(model, q, model.target_offset, jacobian=False).p
    assert np.abs(p - theirs[:, :3, 3]).max() < 1e-9
    turn = np.swapaxes(ours[:, :3, :3], 1, 2) @ theirs[:, :3, :3]
    assert np.abs(turn - turn[0]).max() < 1e-9
    w = so3_log(turn[0])
    assert abs(np.linalg.norm(w) - 0.1) < 1e-9
    axis = ", ".join(f"{round(float(v), 4) + 0.0:g}" for v in w / np.linalg.norm(w))
    assert f"about ({axis})" in line, line
    numbers = re.search(r"at \(([^)]*)\) mm", line)
    assert numbers is not None, line
    np.testing.assert_allclose(
        [float(v) for v in numbers.group(1).split(",")], model.target_offset_xyz, atol=1e-6
    )
    # On the command line: one warning line on stderr, and the command goes on.
    joints = tmp_path / "joints.csv"
    joints.write_text("q1,q2,q3,q4,q5,q6\n0,-90,0,-90,0,0\n")
    run = _cli("predict", "--model", str(path), "--joints", str(joints))
    assert run.returncode == 0, run.stderr
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("cellcal: warning: ")
    assert math.isfinite(float(run.stdout.splitlines()[1].split(",")[-1]))
