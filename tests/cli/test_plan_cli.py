"""`cellcal plan`: every pose, reachable or not, the condition number, the identified
parameters and the cell time, without connecting to anything."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

from tests.conftest import TRACKER_CELL


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cellcal", *args], capture_output=True, text=True, timeout=120
    )


def test_the_plan_its_csv_and_its_json(tmp_path):
    run = _cli("plan", "--config", str(TRACKER_CELL))
    assert run.returncode == 0, run.stderr
    assert "128 poses (80 calibration, 48 validation), 2 unreachable" in run.stdout
    assert "condition number" in run.stdout and "left at nominal: theta1" in run.stdout
    out = tmp_path / "plan.csv"
    run = _cli("plan", "--config", str(TRACKER_CELL), "--out", str(out), "--json")
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    assert (s["n_poses"], s["n_calibration"], s["n_unreachable"]) == (128, 80, 2)
    assert "theta1" in s["unidentifiable"] and "a2" in s["identified"]
    assert s["condition_number"] > 1 and s["cell_time_min"] > 128 * 7 / 60
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert list(rows[0])[:10] == [
        "idx",
        "role",
        "region",
        "reachable",
        "q1",
        "q2",
        "q3",
        "q4",
        "q5",
        "q6",
    ]
    assert list(rows[0])[10:13] == ["x", "y", "z"]
    assert len(rows) == 130
    assert sum(r["reachable"] == "no" for r in rows) == 2
    assert all(r["q1"] == "" for r in rows if r["reachable"] == "no")


def test_optimal_picks_n_calibration_poses(tmp_path):
    run = _cli("plan", "--mock", "--optimal", "24", "--json")
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    assert s["n_calibration"] == 24 and s["optimal"]["n"] == 24
    assert s["optimal"]["candidates"] == 320


def test_bad_requests_are_one_line(tmp_path):
    run = _cli("plan", "--mock", "--optimal", "5")
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "identifiable parameters" in run.stderr
    run = _cli("plan", "--mock", "--optimal", "5000")
    assert run.returncode == 2 and "candidates" in run.stderr
    far = tmp_path / "far.toml"
    far.write_text(
        TRACKER_CELL.read_text().replace(
            "cube_centre_mm = [750.0, 0.0, 1000.0]", "cube_centre_mm = [750.0, 0.0, 1950.0]"
        )
    )
    run = _cli("plan", "--config", str(far))
    assert run.returncode == 0, run.stderr
    assert "unreachable: outside the workspace box" in run.stdout
