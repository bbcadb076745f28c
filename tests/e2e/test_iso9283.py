"""The ISO 9283 test in mock mode: a campaign calibrates the simulated robot; the test
then moves it through the standard's five points with the nominal model's joints and
with the calibrated model's, through the real drivers, and stores every sample."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from cellcal.calib.iso9283 import iso_points
from tests.conftest import TRACKER_CELL
from tests.e2e.calibrated import calibrated_campaign, cli

pytestmark = pytest.mark.timeout(300)


def test_accuracy_improves_repeatability_stays_and_every_sample_is_stored(tmp_path):
    config, _, outcome, model_path = calibrated_campaign(tmp_path)
    model = str(model_path)
    iso_db = str(tmp_path / "iso.db")
    cycles = 6
    run = cli(
        "iso9283",
        "--mock",
        "--config",
        str(TRACKER_CELL),
        "--model",
        model,
        "--db",
        iso_db,
        "--cycles",
        str(cycles),
        "--json",
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)["iso9283"]
    before, after = out["iso-before"]["points"], out["iso-after"]["points"]
    points = iso_points(np.array(config.campaign.cube_centre_mm), config.campaign.cube_edge_mm)
    for stage in (before, after):
        assert [p["point"] for p in stage] == ["P1", "P2", "P3", "P4", "P5"]
        np.testing.assert_allclose([p["commanded_mm"] for p in stage], points)
        assert all(p["n"] == cycles for p in stage)
    ap_b = np.array([p["ap_mm"] for p in before])
    ap_a = np.array([p["ap_mm"] for p in after])
    rp_a = np.array([p["rp_mm"] for p in after])
    print(f"AP before {ap_b.round(4)}, after {ap_a.round(4)}; RP after {rp_a.round(4)} mm")
    # The nominal model misses by the injected errors; the calibrated one by about the
    # validation error inside the cube.
    assert ap_b.min() > 0.2
    assert ap_a.max() < 0.05 * ap_b.min()
    assert ap_a.max() < 3 * outcome.summary.inside.after.rms
    # The simulated robot returns exactly: RP is the tracker's noise on 20-sample means.
    assert rp_a.max() < 0.05
    conn = sqlite3.connect(iso_db)
    try:
        n_poses, status = conn.execute("SELECT n_poses, status FROM campaigns").fetchone()
        assert (n_poses, status) == (2 * 5 * cycles, "complete")
        samples = conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        assert samples == n_poses * config.campaign.samples_per_pose
        roles = dict(conn.execute("SELECT role, COUNT(*) FROM poses GROUP BY role").fetchall())
        assert roles == {"iso-before": 5 * cycles, "iso-after": 5 * cycles}
    finally:
        conn.close()
    # The report shows the test.
    run = cli("report", "--db", iso_db, "--out", str(tmp_path / "iso-report"))
    assert run.returncode == 0, run.stderr
    assert "ISO 9283 pose accuracy" in (tmp_path / "iso-report" / "index.html").read_text()


def test_a_nominal_model_and_too_few_cycles_are_refused(tmp_path):
    run = cli("iso9283", "--mock", "--model", "kuka-kr5-arc", "--db", str(tmp_path / "x.db"))
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "calibrated model" in run.stderr
    run = cli("iso9283", "--mock", "--model", "kuka-kr5-arc", "--cycles", "1")
    assert run.returncode == 2
