"""The issue's own scenario: `cellcal run` with the real drivers against a standalone
`cellcal mock tracker` and `cellcal mock modbus-robot`. Each twin simulates its own cell,
so the tracker measures a target that does not follow the robot that moves: the
campaign stores every sample, is refused with exit 3, and nothing claims success."""

from __future__ import annotations

import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.twin

TRACKER = ("127.0.0.71", 5555)
ROBOT = ("127.0.0.72", 1502)

CONFIG = f"""
name = "standalone twins"
[robot]
model = "kuka-kr5-arc"
driver = "modbus"
address = "{ROBOT[0]}:{ROBOT[1]}"
home_deg = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
move_timeout_s = 20.0
[[sensor]]
name = "tracker"
kind = "laser-tracker"
driver = "line-protocol"
address = "socket://{TRACKER[0]}:{TRACKER[1]}"
rate_hz = 10.0
target_offset_mm = [25.0, -40.0, 130.0]
reference = true
[campaign]
grid = [2, 2, 3]
dwell_s = 0.1
samples_per_pose = 3
validation_inside = 4
validation_regions_mm = [[1000.0, 150.0, 550.0]]
validation_per_region = 2
"""


def config_on(tracker: tuple[str, int], robot: tuple[str, int]) -> str:
    """This cell on other addresses (for other tests' own twins)."""
    text = CONFIG.replace(f"{TRACKER[0]}:{TRACKER[1]}", f"{tracker[0]}:{tracker[1]}")
    return text.replace(f"{ROBOT[0]}:{ROBOT[1]}", f"{robot[0]}:{robot[1]}")


def _wait_listening(address: tuple[str, int], proc: subprocess.Popen[str], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(address, timeout=0.5).close()
            return
        except OSError:
            assert proc.poll() is None, f"twin ended: {proc.communicate()[1]}"
            assert time.monotonic() < deadline, f"nothing listens on {address}"
            time.sleep(0.01)


def _twin(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", *args, "--time-scale", "0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_run_against_standalone_twins_is_refused_and_keeps_every_sample(tmp_path: Path) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(CONFIG)
    db = tmp_path / "c.db"
    twins = [
        _twin("tracker", "--listen", f"{TRACKER[0]}:{TRACKER[1]}"),
        _twin("modbus-robot", "--listen", f"{ROBOT[0]}:{ROBOT[1]}"),
    ]
    try:
        _wait_listening(TRACKER, twins[0], 30.0)
        _wait_listening(ROBOT, twins[1], 30.0)
        res = subprocess.run(
            [sys.executable, "-m", "cellcal", "run", "--config", str(config), "--db", str(db)],
            capture_output=True,
            text=True,
            timeout=180,
            check=False,
        )
    finally:
        for t in twins:
            t.kill()
            t.wait(timeout=10)
    assert res.returncode == 3, res.stderr
    err = [line for line in res.stderr.splitlines() if line.startswith("cellcal:")]
    assert len(err) == 1 and res.stderr.strip().splitlines()[-1] == err[0]  # after progress
    assert err[0].startswith("cellcal: refused: target does not follow the robot")
    assert "every sample is stored" in err[0] and "--accept" in err[0]
    assert "complete" not in res.stdout and "reduction" not in res.stdout
    with sqlite3.connect(db) as con:
        (status,) = con.execute("SELECT status FROM campaigns").fetchone()
        (poses,) = con.execute("SELECT count(*) FROM poses").fetchone()
        (samples,) = con.execute("SELECT count(*) FROM samples").fetchone()
        (calibrations,) = con.execute("SELECT count(*) FROM calibrations").fetchone()
    assert status == "refused"
    assert poses == 12 + 4 + 2
    assert samples == poses * 3
    assert calibrations == 0
