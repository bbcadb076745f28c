"""`cellcal plan`: every pose, reachable or not, the condition number, the identified
parameters and the cell time, without connecting to anything; what it is doing on stderr
when it chooses or draws poses; the region its expected error covers."""

from __future__ import annotations

import csv
import io
import json
import math
import subprocess

import pytest

from tests.conftest import TRACKER_CELL
from tests.inprocess import cellcal


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return cellcal(*args)


def test_the_mock_cells_plan_is_printed():
    run = _cli("plan", "--mock")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    # A header, one line per pose (idx, role, region, six joints, target), then the numbers.
    rows = [line.split() for line in lines]
    poses = [r for r in rows if r[:1] and r[0].isdigit() and r[1] in ("calibration", "validation")]
    assert len(poses) == 128 and [int(p[0]) for p in poses] == list(range(128))
    assert poses[0][1:3] == ["calibration", "cube"] and len(poses[0]) == 3 + 6 + 3
    assert sum("unreachable: no joint solution within the limits" in x for x in lines) == 2
    assert "128 poses (80 calibration, 48 validation), 2 unreachable" in run.stdout
    assert "condition number " in run.stdout and "left at nominal: theta1" in run.stdout
    # The numbers the calibration prints for these poses: the condition number with equal
    # weights (the fit's own weighs each coordinate by its σ), 21 parameters identified.
    assert "with equal weights (the calibration weighs each coordinate" in run.stdout
    assert (
        "identifies 21 parameters of the robot and target offset (+ 6 of the sensor frame): "
        "a1, alpha1, " in run.stdout
    )
    assert "; sensor frame: frame_rx, frame_ry, frame_rz, frame_x, frame_y, frame_z" in run.stdout
    assert "7 s dwell per pose, moves at 15 °/s" in run.stdout
    assert "expected RMS error in the cube and the validation regions" in run.stdout
    assert run.stderr == ""  # nothing slow, nothing said


def test_the_plans_csv_and_json(tmp_path):
    out = tmp_path / "plan.csv"
    run = _cli("plan", "--config", str(TRACKER_CELL), "--out", str(out), "--json")
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    assert {
        "config",
        "model",
        "n_poses",
        "n_calibration",
        "n_validation",
        "n_unreachable",
        "regions",
        "condition_number",
        "condition_number_equal_weights",
        "identified",
        "identified_frame",
        "unidentifiable",
        "region",
        "expected_region",
        "expected_points",
        "dwell_s",
        "joint_speed_deg_s",
        "cell_time_min",
        "out",
        "poses",
    } <= set(s)
    assert (s["n_poses"], s["n_calibration"], s["n_unreachable"]) == (128, 80, 2)
    assert "theta1" in s["unidentifiable"] and "a2" in s["identified"]
    # As the calibration counts them: the robot's and the target offset's; the frame apart.
    assert len(s["identified"]) == 21 and s["identified"][-3:] == [
        "target_offset_x",
        "target_offset_y",
        "target_offset_z",
    ]
    assert s["identified_frame"] == [
        "frame_rx",
        "frame_ry",
        "frame_rz",
        "frame_x",
        "frame_y",
        "frame_z",
    ]
    assert 1 < s["condition_number"] == s["condition_number_equal_weights"] < 1000
    assert (
        s["region"] == "cube" and s["expected_region"] == "in the cube and the validation regions"
    )
    assert s["expected_points"] > 100
    assert s["cell_time_min"] > 128 * 7 / 60
    assert len(s["poses"]) == 130 and s["poses"][-1]["reachable"] is False
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert list(rows[0])[:13] == [
        "idx",
        "role",
        "region",
        "reachable",
        *(f"q{i}" for i in range(1, 7)),
        "x",
        "y",
        "z",
    ]
    assert len(rows) == 130  # every pose, the 2 unreachable ones too
    assert sum(r["reachable"] == "no" for r in rows) == 2
    assert all(r["q1"] == "" and r["reason"] for r in rows if r["reachable"] == "no")
    first = s["poses"][0]
    assert abs(float(rows[0]["q1"]) - first["q_deg"][0]) < 1e-5
    assert abs(float(rows[0]["z"]) - first["target_mm"][2]) < 1e-5


def test_optimal_picks_n_calibration_poses(tmp_path):
    out = tmp_path / "plan.csv"
    run = _cli("plan", "--mock", "--optimal", "24", "--json", "--out", str(out))
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    assert s["n_calibration"] == 24 and s["optimal"]["n"] == 24
    assert s["optimal"]["candidates"] == 320
    assert (s["optimal"]["candidates_drawn"], s["optimal"]["candidates_unreachable"]) == (320, 0)
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert sum(r["role"] == "calibration" for r in rows) == 24
    assert len(rows) == 24 + 48 + 2
    assert s["optimal"]["criterion"] == "D"
    # I-optimal poses are expected to predict better in the cube and the regions.
    run = _cli("plan", "--mock", "--optimal", "24", "--criterion", "I", "--json")
    assert run.returncode == 0, run.stderr
    # Progress on stderr (the JSON alone on stdout): first what it will do, then the
    # candidates it found.
    said = run.stderr.splitlines()
    assert said[0] == "planning: 24 I-optimal calibration poses from candidates of the cube …"
    assert said[1] == (
        "planning: 320 reachable candidates of 320 in the cube (0 unreachable); "
        "choosing 24 (I-optimal) …"
    )
    i = json.loads(run.stdout)
    assert i["optimal"]["criterion"] == "I" and i["n_calibration"] == 24
    assert i["expected_rms_sigma"] < 0.9 * s["expected_rms_sigma"]
    history = i["optimal"]["history"]
    assert history[-1] == min(history)
    assert math.isclose(history[-1] ** 0.5, i["expected_rms_sigma"], rel_tol=1e-6)


def _refusal(run: subprocess.CompletedProcess[str]) -> str:
    """The one error line, after the plan's progress lines."""
    *said, last = run.stderr.splitlines()
    assert run.returncode == 2 and all(line.startswith("planning: ") for line in said)
    assert last.startswith("cellcal: error: ")
    return last


def test_bad_requests_are_one_line(tmp_path):
    run = _cli("plan", "--mock", "--optimal", "5")
    assert "identifiable parameters; choose at least 10" in _refusal(run)
    run = _cli("plan", "--mock", "--optimal", "5000")
    assert "5000 poses asked for, 320 reachable candidates" in _refusal(run)
    far = tmp_path / "far.toml"
    far.write_text(
        TRACKER_CELL.read_text().replace(
            "cube_centre_mm = [750.0, 0.0, 1000.0]", "cube_centre_mm = [750.0, 0.0, 1950.0]"
        )
    )
    run = _cli("plan", "--config", str(far), "--out", str(tmp_path / "far.csv"))
    assert run.returncode == 0, run.stderr
    assert "unreachable: outside the workspace box" in run.stdout
    rows = list(csv.DictReader(io.StringIO((tmp_path / "far.csv").read_text())))
    boxed = [r for r in rows if r["reason"] == "outside the workspace box"]
    assert any(r["role"] == "calibration" for r in boxed)
    assert all(r["reachable"] == "no" and r["q1"] == "" for r in boxed)


@pytest.mark.slow
def test_the_workspace_region(tmp_path):
    run = _cli("plan", "--mock", "--optimal", "30", "--region", "workspace", "--json")
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    box = "x -1500..1500, y -1500..1500, z 0..2000 mm"
    assert s["region"] == "workspace" and s["expected_region"] == f"over the workspace box ({box})"
    assert s["expected_points"] == 200
    o = s["optimal"]
    assert (o["n"], o["candidates"]) == (30, 320)
    assert o["candidates_drawn"] == 320 + o["candidates_unreachable"] > 320
    cal = [p for p in s["poses"] if p["role"] == "calibration"]
    assert len(cal) == 30 and {p["region"] for p in cal} == {"workspace"}
    assert s["regions"]["validation cube"] == 20  # the validation poses stay where they were
    assert s["expected_rms_sigma"] < 2  # on the cube's poses: about 7
    said = run.stderr.splitlines()
    assert said[0] == (
        "planning: 30 D-optimal calibration poses from candidates drawn over the workspace box …"
    )
    assert any(x.startswith("planning: 320 reachable candidates of ") for x in said)
    # Without --optimal: the cube's poses, their expected error judged over the box.
    run = _cli("plan", "--mock", "--region", "workspace")
    assert run.returncode == 0, run.stderr
    assert "128 poses (80 calibration, 48 validation)" in run.stdout
    assert f"expected RMS error over the workspace box ({box}) after calibration: " in run.stdout
    assert "judged at 200 reachable poses" in run.stdout
    assert run.stderr.startswith("planning: the expected error is judged at poses drawn over")
