"""SIGHUP (``systemctl reload cellcal``) reads the configuration file again: the next
campaign plans with the new file; a file the service would refuse — here one whose rig
calibration is missing — is logged in one line and the configuration in use is kept."""

from __future__ import annotations

import json
import shutil
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from cellcal.commands.service_client import call
from tests.daemon.conftest import Daemon
from tests.inprocess import cellcal

ROOT = Path(__file__).resolve().parents[2]
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"
RIG_CELL = ROOT / "config" / "mock-cell.toml"

pytestmark = [pytest.mark.twin, pytest.mark.timeout(180)]


def _logged(d: Daemon, text: str, timeout: float = 60) -> None:
    """Wait until the service's log has ``text`` (polled: no fixed sleep)."""
    deadline = time.monotonic() + timeout
    while text not in d.tail():
        assert d.proc is not None and d.proc.poll() is None, d.tail()
        assert time.monotonic() < deadline, f"never logged {text!r}:\n{d.tail()}"
        time.sleep(0.05)


def _planned(d: Daemon) -> int:
    """The poses a campaign of the service's own configuration plans (it is aborted)."""
    cid = call(d.sock, "POST", "/v1/campaigns", {})["campaign_id"]
    # this campaign under way (the status shows the last one until it starts)
    d.until(lambda s: s["state"] == "running" and (s.get("campaign") or {}).get("id") == cid)
    call(d.sock, "POST", "/v1/campaigns/current/abort", {})
    d.until(lambda s: s["state"] == "idle", 60)
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {cid}") == [("aborted",)]
    ((planned,),) = d.rows(f"SELECT n_poses FROM campaigns WHERE id = {cid}")
    return int(planned)


def _plan(path: Path) -> int:
    """The poses ``cellcal plan`` plans for the file."""
    done = cellcal("plan", "--config", str(path), "--json")
    assert done.returncode == 0, done.stderr
    return int(json.loads(done.stdout)["n_poses"])


def test_sighup_applies_a_good_file_and_keeps_the_old_one_for_a_bad_file(
    folder: Path, daemon: Callable[..., Daemon]
) -> None:
    cell = folder / "cell.toml"
    shutil.copy(TRACKER_CELL, cell)
    d = daemon(folder, None, 0.02, config=cell)
    d.start()
    before = _planned(d)
    assert before == _plan(cell)

    text = cell.read_text()
    assert "grid = [4, 4, 5]\n" in text
    cell.write_text(text.replace("grid = [4, 4, 5]\n", "grid = [2, 2, 3]\n"))
    assert d.proc is not None
    d.proc.send_signal(signal.SIGHUP)
    _logged(d, f"SIGHUP: {cell} read again; applied when no campaign runs")
    after = _planned(d)
    assert after == _plan(cell) and after < before

    # the rig cell, whose rig calibration is not beside it: refused, the file in use kept
    cell.write_text(RIG_CELL.read_text().replace("grid = [4, 4, 5]\n", "grid = [3, 3, 3]\n"))
    d.proc.send_signal(signal.SIGHUP)
    _logged(
        d,
        f"SIGHUP: {cell}: sensor.2.rig_file = {folder}/mock-rig.toml: no such file; "
        "the configuration in use is kept",
    )
    assert _planned(d) == after
    status = d.status()
    assert set(status["devices"]) == {"robot", "tracker"}
    assert all(v["state"] == "ready" for v in status["devices"].values())
    assert d.stop() == 0
