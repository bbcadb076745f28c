"""A protective stop in the middle of a mock campaign, through each robot family that
drives a program on its controller (KUKA over KUKAVARPROXY and EthernetKRL, ABB over Robot
Web Services, FANUC over RMI, Yaskawa over HSES): the campaign ends in one line naming
the robot and the resume command, keeps every pose it stored, and `run --resume`
completes it with every planned pose stored exactly once."""

from __future__ import annotations

import re
import sqlite3
import tomllib
from pathlib import Path

import pytest
import tomli_w

from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(300)]

ROOT = Path(__file__).resolve().parents[2]
SAYS = {
    "kuka-kvp": "a stop message is active",
    "kuka-eki": "a stop message is active",
    "abb-rws": "RAPID is not running",
    "fanuc-rmi": "system fault during the move",
    "yaskawa-hses": "move failed: alarm 4000",
}


@pytest.mark.parametrize("driver", sorted(SAYS))
def test_a_protective_stop_is_one_line_and_the_campaign_resumes(tmp_path: Path, driver: str):
    if driver == "abb-rws":
        pytest.importorskip("httpx")
    cell = tomllib.loads((ROOT / "config" / f"mock-cell-{driver}.toml").read_text())
    cell["campaign"] |= {
        "grid": [2, 2, 3],
        "samples_per_pose": 3,
        "validation_inside": 3,
        "validation_per_region": 1,
    }
    cell.setdefault("simulation", {})["faults"] = {"robot_protective_stop_every": 9}
    config = tmp_path / "cell.toml"
    config.write_text(tomli_w.dumps(cell))
    db = tmp_path / "c.db"
    done = cellcal("run", "--mock", "--config", config, "--db", db)
    assert done.returncode == 2, done.stderr[-2000:]
    last = done.stderr.strip().splitlines()[-1]
    assert SAYS[driver] in last and re.search(r"robot at (http://)?127\.0\.0\.\d+:\d+: ", last)
    assert "cellcal run --resume 1" in done.stderr
    conn = sqlite3.connect(db)
    stored = conn.execute("SELECT COUNT(*) FROM poses").fetchone()[0]
    assert stored == 8  # the 9th move stopped
    conn.close()
    for _ in range(10):  # every 9th move of each run stops again: resume until complete
        done = cellcal("run", "--resume", "1", "--db", db)
        if done.returncode == 0:
            break
        assert SAYS[driver] in done.stderr.strip().splitlines()[-1], done.stderr[-2000:]
    assert done.returncode == 0, done.stderr[-2000:]
    conn = sqlite3.connect(db)
    (status,) = conn.execute("SELECT status FROM campaigns WHERE id = 1").fetchone()
    idx = [i for (i,) in conn.execute("SELECT idx FROM poses ORDER BY idx")]
    per_pose = {n for (n,) in conn.execute("SELECT COUNT(*) FROM samples GROUP BY pose_id")}
    assert status == "complete" and idx == sorted(set(idx)) and per_pose == {3}
