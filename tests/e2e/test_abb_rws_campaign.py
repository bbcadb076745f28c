"""A mock campaign with an ABB robot through Robot Web Services (issue 32): the real
abb-rws driver against the ABB twin (an IRC5 running cellcal's RAPID module, RWS 1.0 with
digest authentication) over HTTP. Every pose is moved to, acknowledged, read back from the
mechanical unit's jointtarget and measured; the calibration finds the simulated errors as
it does behind Modbus."""

from __future__ import annotations

import json
import sqlite3
import tomllib
from pathlib import Path

import pytest
import tomli_w

from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(240)]

ROOT = Path(__file__).resolve().parents[2]


def test_an_abb_rws_campaign_is_stored_and_calibrated(tmp_path: Path):
    cell = tomllib.loads((ROOT / "config" / "mock-cell-abb-rws.toml").read_text())
    cell["campaign"] |= {
        "grid": [3, 3, 3],
        "samples_per_pose": 5,
        "validation_inside": 4,
        "validation_per_region": 2,
    }
    config = tmp_path / "cell.toml"
    config.write_text(tomli_w.dumps(cell))
    db = tmp_path / "a.db"
    done = cellcal("run", "--mock", "--config", config, "--db", db, "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)
    conn = sqlite3.connect(db)
    per_pose = conn.execute("SELECT COUNT(*) FROM samples GROUP BY pose_id").fetchall()
    assert len(per_pose) >= 27 and {n for (n,) in per_pose} == {5}
    (device,) = conn.execute(
        "SELECT message FROM events WHERE kind = 'device' AND message LIKE '%abb-rws%'"
    ).fetchone()
    assert '"maker": "ABB"' in device
    # the joints stored are the measured ones, at the targets
    for planned, reached in conn.execute("SELECT planned_q_deg, reached_q_deg FROM poses"):
        assert json.loads(reached) == pytest.approx(json.loads(planned), abs=1e-3)
    # 27 calibration poses: the simulated 0.3 mm / 0.03° errors found as behind Modbus
    assert summary["improvement_pct"] > 85, summary["validation_after"]
    assert summary["inside"]["after"]["rms_mm"] < 0.02
