"""Campaigns that make error terms identifiable. Payload sessions on the simulated
cell: a UR5e (its published mass model) that yields under gravity
(``[simulation.terms]``), measured at 0 and 5 kg (``[campaign] payloads_kg``). The
campaign pauses before the second payload with the instruction, resuming is the
operator's word that it is mounted, and the calibration then accepts compliance and
predicts both payloads to the noise. Repeated reference poses measure a warming cell's
drift directly."""

from __future__ import annotations

import json
import sqlite3
import tomllib
from pathlib import Path

import pytest
import tomli_w

from tests.conftest import small_tracker_file
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(300)]

ROOT = Path(__file__).resolve().parents[2]
#: the simulated robot's compliance at joints 2, 3, 4 (deg per kN·m)
COMPLIANCE = [0.0, 0.5, 0.8, 1.0, 0.0, 0.0]


def _cell(folder: Path, payloads: list[float]) -> Path:
    cell = tomllib.loads((ROOT / "config" / "mock-cell-ur10e.toml").read_text())
    cell["name"] = "simulated UR5e cell with payloads"
    cell["robot"]["model"] = "ur5e"
    cell["campaign"] |= {
        "cube_centre_mm": [-450.0, -150.0, 350.0],
        "grid": [3, 3, 4],
        "samples_per_pose": 2,
        "validation_inside": 6,
        "validation_per_region": 0,
        "workspace_min_mm": [-900.0, -900.0, -100.0],
        "workspace_max_mm": [900.0, 900.0, 900.0],
        "payloads_kg": payloads,
    }
    cell["simulation"]["terms"] = {"compliance_deg_per_knm": COMPLIANCE}
    path = folder / "cell.toml"
    path.write_text(tomli_w.dumps(cell))
    return path


def test_the_campaign_pauses_for_each_payload_and_finds_the_compliance(tmp_path: Path) -> None:
    config, db = _cell(tmp_path, [0.0, 5.0]), tmp_path / "cell.db"
    first = cellcal("run", "--mock", "--config", config, "--db", db)
    assert first.returncode == 130, first.stderr[-2000:]
    said = first.stderr.strip().splitlines()[-1]
    assert "paused with 42 of 84 poses stored: mount the 5 kg payload" in said
    assert f"cellcal run --resume 1 --db {db}" in said
    with sqlite3.connect(db) as conn:
        status = conn.execute("SELECT status FROM campaigns").fetchone()[0]
        kinds = [k for (k,) in conn.execute("SELECT kind FROM events ORDER BY id")]
    assert status == "paused" and "payload-change" in kinds

    done = cellcal("run", "--resume", "1", "--db", db, "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    with sqlite3.connect(db) as conn:
        payloads = [m for (m,) in conn.execute("SELECT message FROM events WHERE kind='payload'")]
        model = tomllib.loads(conn.execute("SELECT model_toml FROM calibrations").fetchone()[0])
    assert payloads == ["0 kg payload on the robot", "5 kg payload mounted (the campaign resumed)"]
    # the UR's joint temperatures, read through ur_rtde at every pose
    with sqlite3.connect(db) as conn:
        logged = conn.execute(
            "SELECT pose_idx, message FROM events WHERE kind = 'robot-temperature'"
        ).fetchall()
    assert sorted(i for i, _ in logged) == list(range(84))
    assert all(20.0 < t < 40.0 for _, m in logged for t in json.loads(m)["joints_c"])
    assert model["fit"]["terms"]["accepted"] == ["compliance"]
    joints = {t["joint"]: t["coefficients"][0] for t in model["term"]}
    assert 0.35 < joints[2] < 0.65  # what the poses can tell apart of joints 2–4
    assert model["validation"]["after_rms_mm"] < 0.03  # both payloads, to the noise

    # The report's measurement file carries what the terms read, so a calibration from
    # the file alone finds the same compliance as the campaign's.
    report = cellcal("report", "--db", db, "--out", tmp_path / "report")
    assert report.returncode == 0, report.stderr[-2000:]
    data = tmp_path / "report" / "measurements-tracker.csv"
    head, *rows = [line.split(",") for line in data.read_text().splitlines()]
    assert head[-3:] == ["time_s", "temperature_c", "payload_kg"]
    assert {float(r[-1]) for r in rows} == {0.0, 5.0}
    assert all(20.0 < float(r[-2]) < 40.0 for r in rows)  # the joints' mean, °C
    times = [float(r[-3]) for r in rows]
    assert times == sorted(times) and times[0] >= 0.0
    again = cellcal("calibrate", "--model", "ur5e", "--data", data, "--folds", "0", "--json")
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(again.stdout)["terms"]["accepted"] == ["compliance"]


def test_payloads_are_each_planned_once(tmp_path: Path) -> None:
    config = _cell(tmp_path, [5.0, 5.0])
    done = cellcal("plan", "--config", config)
    assert done.returncode == 2
    assert "payloads_kg: each payload once" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_reference_poses_measure_a_warming_cells_drift(tmp_path: Path) -> None:
    """Two reference poses measured every ten poses while the simulated arm warms by
    10 °C over the campaign: the drift they measure is far beyond its uncertainty, and
    the drift term, judged on later stretches, is accepted."""
    warming = {"thermal_mm_per_c": 0.05, "temperature_c": [[0.0, 20.0], [2000.0, 30.0]]}
    config = small_tracker_file(
        tmp_path,
        "warm",
        [4, 4, 4],
        3,
        6,
        campaign={"reference_poses": 2, "reference_every": 10},
        simulation={"change": warming},
    )
    done = cellcal("run", "--mock", "--config", config, "--db", tmp_path / "warm.db", "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout)
    refs = summary["reference_poses"]
    assert [r["pose"] for r in refs] == ["ref1", "ref2"] and all(r["n"] == 8 for r in refs)
    for r in refs:
        assert r["drift_mm_per_h"] > 3 * r["drift_sigma_mm_per_h"]
        assert r["repeatability_mm"] < 0.06  # the drift over ten minutes, the noise below
    assert summary["n_calibration_poses"] == 64  # the reference poses are not fitted
    with sqlite3.connect(tmp_path / "warm.db") as conn:
        model = tomllib.loads(conn.execute("SELECT model_toml FROM calibrations").fetchone()[0])
    assert "drift" in model["fit"]["terms"]["accepted"]


def test_the_simulated_cells_ratio_errors_are_found_by_its_campaign(tmp_path: Path) -> None:
    """``[simulation.terms] ratio_pct``: the simulated KR 5 arc's joints 2 and 3 turning
    0.05 % less and 0.04 % more than they read. The mock campaign, through the real
    twins, accepts the ratio term and finds both within their uncertainty."""
    truth = [0.0, -0.05, 0.04, 0.0, 0.0, 0.0]
    config = small_tracker_file(
        tmp_path, "ratio", [4, 4, 4], 3, 6, simulation={"terms": {"ratio_pct": truth}}
    )
    db = tmp_path / "ratio.db"
    done = cellcal("run", "--mock", "--config", config, "--db", db, "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    with sqlite3.connect(db) as conn:
        model = tomllib.loads(conn.execute("SELECT model_toml FROM calibrations").fetchone()[0])
    assert model["fit"]["terms"]["accepted"] == ["ratio"]
    found = {t["joint"]: t for t in model["term"] if t["name"] == "ratio"}
    for joint in (2, 3):
        t = found[joint]
        assert t["units"] == ["%"]
        error, sigma = abs(t["coefficients"][0] - truth[joint - 1]), t["sigma"][0]
        assert error < 4 * sigma and sigma < 0.02, t
