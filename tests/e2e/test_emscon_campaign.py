"""A mock campaign with a Leica tracker on emScon TPI (issue 31): the real emScon driver
against the emScon twin over TCP, through a warm-up and beam breaks the simulation
injects. Every pose keeps exactly ``samples_per_pose`` samples, each with its covariance
and the air the tracker compensated with; the breaks are recorded."""

from __future__ import annotations

import sqlite3
import tomllib
from pathlib import Path

import pytest
import tomli_w

from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(240)]

ROOT = Path(__file__).resolve().parents[2]


def test_an_emscon_campaign_stores_every_sample_with_covariance_and_air(tmp_path: Path):
    cell = tomllib.loads((ROOT / "config" / "mock-cell-emscon.toml").read_text())
    cell["campaign"] |= {
        "grid": [3, 3, 3],
        "samples_per_pose": 6,
        "validation_inside": 4,
        "validation_per_region": 2,
    }
    cell["simulation"]["faults"] = {
        "tracker_warmup_s": 0.3,
        "tracker_beam_break_every": 7,
        "tracker_beam_restore_s": 0.05,
    }
    config = tmp_path / "cell.toml"
    config.write_text(tomli_w.dumps(cell))
    db = tmp_path / "e.db"
    done = cellcal("-v", "run", "--mock", "--config", config, "--db", db)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "laser warming up" in done.stderr
    conn = sqlite3.connect(db)
    per_pose = conn.execute(
        """SELECT COUNT(*), COUNT(cov_xy), COUNT(temperature_c), MIN(pressure_hpa)
        FROM samples GROUP BY pose_id"""
    ).fetchall()
    assert len(per_pose) >= 27
    assert {(n, c, t) for n, c, t, _ in per_pose} == {(6, 6, 6)}
    assert all(900 < p < 1100 for *_, p in per_pose)
    notes = [m for (m,) in conn.execute("SELECT message FROM events WHERE kind = 'sensor-note'")]
    assert notes and all("no stationary result" in m for m in notes)
    assert all("6 of 6 samples after 7 attempts" in m for m in notes)
    (family,) = conn.execute(
        "SELECT message FROM events WHERE kind = 'device' AND message LIKE '%emscon%'"
    ).fetchone()
    assert '"maker": "Leica"' in family and '"model": "AT401"' in family
