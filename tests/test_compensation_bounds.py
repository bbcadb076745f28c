"""Compensation refuses answers that cannot be right (issue 29, item 5): joints outside
the limits, a flange (or target) inside the robot's base, joints far from the nominal
model's solution or a correction beyond manufacturing tolerances: exit 3 with the
likely cause, nothing written. A model without limits is refused (exit 2)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from cellcal.calib.compensation import compensate
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import measure, random_cell, random_joints
from tests.inprocess import cellcal

KR5 = load_model("kuka-kr5-arc").model
TOOL = np.array([25.0, -40.0, 130.0])
HOME = np.radians([0.0, -30.0, 40.0, 0.0, -20.0, 0.0])
#: Points the KR 5 arc reaches with its joints in range, in front of it.
GOOD = np.array([[750.0, 0.0, 1000.0], [800.0, 100.0, 900.0]])


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> Path:
    """A KR 5 arc calibrated from simulated measurements (``cellcal calibrate --out``)."""
    folder = tmp_path_factory.mktemp("cal")
    rng = np.random.default_rng(5)
    cell = random_cell(KR5, rng, target_offset_mm=tuple(TOOL))
    q = random_joints(KR5, rng, 60, span=0.6)
    xyz = measure(cell, q, rng, 0.01)
    rows = [",".join(f"{v:.9f}" for v in (*np.degrees(a), *b)) for a, b in zip(q, xyz, strict=True)]
    data = folder / "m.csv"
    data.write_text("q1,q2,q3,q4,q5,q6,x,y,z\n" + "\n".join(rows) + "\n")
    out = folder / "cal.toml"
    run = cellcal("calibrate", "--model", "kuka-kr5-arc", "--data", data, "--out", out)
    assert run.returncode == 0, run.stderr
    return out


def _targets(path: Path, points: np.ndarray) -> Path:
    path.write_text(
        "name,x,y,z\n" + "".join(f"P{k},{x},{y},{z}\n" for k, (x, y, z) in enumerate(points))
    )
    return path


def _compensate(model: Path, targets: Path, out: Path, *extra: str):
    return cellcal("compensate", "--model", model, "--targets", targets, "--out", out, *extra)


def _refused(run, code: int) -> str:
    lines = run.stderr.strip().splitlines()
    assert run.returncode == code, run.stderr
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    return lines[0]


def _edited(src: Path, dst: Path, change) -> Path:
    doc = tomllib.loads(src.read_text())
    change(doc)
    dst.write_text(tomli_w.dumps(doc))
    return dst


def test_good_points_are_compensated(calibrated, tmp_path):
    out = tmp_path / "j.csv"
    seed = "0,-30,40,0,-20,0"
    run = _compensate(calibrated, _targets(tmp_path / "t.csv", GOOD), out, "--seed-deg", seed)
    assert run.returncode == 0, run.stderr
    assert out.exists()


def test_a_flange_inside_the_base_is_refused(calibrated, tmp_path):
    # Points on the base's axis, below the shoulder: the arm folds onto its base.
    inside = np.array([[0.0, 0.0, 150.0], [50.0, 50.0, 300.0]])
    out = tmp_path / "j.csv"
    run = _compensate(calibrated, _targets(tmp_path / "t.csv", inside), out)
    line = _refused(run, 3)
    assert "inside the robot's base" in line and "P0" in line, line
    assert not out.exists()
    from cellcal.calib.compensation import inside_base

    comp = compensate(KR5, TOOL, KR5, inside, None, np.zeros(6))
    assert inside_base(KR5, inside).all() and not comp.ok.any()
    # The base is the column below the shoulder, not what is above it or beside it.
    assert not inside_base(KR5, np.array([[0.0, 0.0, 600.0], [0.0, 300.0, 100.0]])).any()


def test_joints_outside_the_limits_are_refused_with_exit_3(calibrated, tmp_path):
    # High in front: reached only with A3 below its -15°.
    behind = np.array([[900.0, 0.0, 1500.0]])
    out = tmp_path / "j.csv"
    run = _compensate(calibrated, _targets(tmp_path / "t.csv", behind), out)
    line = _refused(run, 3)
    assert "outside the joint limits" in line and "joint 3" in line, line
    assert not out.exists()


def test_a_correction_beyond_tolerances_is_refused(calibrated, tmp_path):
    def off(doc):  # joint 2 50 mm longer than the robot is: not a manufacturing error
        doc["joint"][1]["a"] += 50.0

    model = _edited(calibrated, tmp_path / "off.toml", off)
    out = tmp_path / "j.csv"
    seed = "0,-30,40,0,-20,0"
    run = _compensate(model, _targets(tmp_path / "t.csv", GOOD), out, "--seed-deg", seed)
    line = _refused(run, 3)
    assert "nominal" in line and "mm" in line, line
    assert not out.exists()


def test_a_calibrated_model_without_limits_is_refused(calibrated, tmp_path):
    def unbounded(doc):
        for row in doc["joint"]:
            row.pop("min", None)
            row.pop("max", None)

    model = _edited(calibrated, tmp_path / "open.toml", unbounded)
    run = _compensate(model, _targets(tmp_path / "t.csv", GOOD), tmp_path / "j.csv")
    assert "joint 1 has no limits" in _refused(run, 2)


@pytest.mark.timeout(120)
def test_iso9283_refuses_a_robot_model_without_limits(calibrated, tmp_path):
    """The ISO 9283 test drives the robot: the cell's model needs limits too."""
    from tests.conftest import TRACKER_CELL

    doc = tomllib.loads(
        (Path(__file__).parents[1] / "cellcal/data/models/kuka-kr5-arc.toml").read_text()
    )
    for row in doc["joint"]:
        row.pop("min")
        row.pop("max")
    model = tmp_path / "open-kr5.toml"
    model.write_text(tomli_w.dumps(doc))
    cell = tmp_path / "cell.toml"
    cell.write_text(
        TRACKER_CELL.read_text().replace('model = "kuka-kr5-arc"', f'model = "{model}"', 1)
    )
    run = cellcal(
        "iso9283",
        "--mock",
        "--config",
        cell,
        "--model",
        calibrated,
        "--db",
        tmp_path / "c.db",
        "--cycles",
        "2",
    )
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr
    assert lines[-1].startswith("cellcal: error: ") and "joint 1 has no limits" in lines[-1]
