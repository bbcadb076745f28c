"""Ctrl-C on a terminal: SIGINT to the whole foreground process group, the campaign's
process and the camera rig's twin (a child process) alike. The child ignores it and is
stopped by its parent; the campaign is recorded as interrupted, exit 130 with the resume
hint, no traceback; ``--resume`` measures the rest, every pose exactly once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.e2e.rig_cell import FAULT_KINDS, count, gige_or_skip, kinds, small_rig_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(300)]


def _wait_for_a_pose(db: Path, proc: subprocess.Popen[str], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while count(db, "SELECT COUNT(*) FROM poses") < 1:
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, f"no pose stored within {timeout} s"
        time.sleep(0.005)


def test_ctrl_c_on_the_rig_campaign_is_an_interrupt_and_resumes(tmp_path):
    gige_or_skip()
    config = small_rig_cell(tmp_path)
    db = tmp_path / "c.db"
    cmd = [sys.executable, "-m", "cellcal", "run", "--mock", "--config", str(config)]
    cmd += ["--db", str(db)]
    # a session of its own: its process group stands for the terminal's foreground group
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        _wait_for_a_pose(db, proc)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C does
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate(timeout=30)
    planned = count(db, "SELECT n_poses FROM campaigns")
    stored = count(db, "SELECT COUNT(*) FROM poses")
    assert 0 < stored < planned, (stored, planned)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "cellcal: SIGINT: finishing cleanly" in err
    assert f"resume with: cellcal run --resume 1 --db {db}" in err
    assert count(db, "SELECT COUNT(*) FROM campaigns WHERE status = 'interrupted'") == 1
    seen = kinds(db)
    assert seen[-1] == "interrupted" and not FAULT_KINDS & set(seen), seen

    res = cellcal("run", "--resume", "1", "--db", db)  # in the test's process
    assert res.returncode == 0, res.stderr
    assert count(db, "SELECT COUNT(*) FROM campaigns WHERE status = 'complete'") == 1
    assert count(db, "SELECT COUNT(*) FROM poses") == planned  # every pose exactly once
    assert count(db, "SELECT COUNT(DISTINCT idx) FROM poses") == planned
    assert count(db, "SELECT MAX(idx) FROM poses") == planned - 1
