"""Ctrl-C on a service run in the foreground: SIGINT to its whole process group, the
camera rig's twin (a child process) included. The service logs SIGINT by its name, stops
its engine at the next safe point, logs no device failure once stopping, exits 0 and
leaves the campaign interrupted (resumable), which a restarted service resumes to the
end, every pose exactly once."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call
from tests.e2e.rig_cell import FAULT_KINDS, gige_or_skip, kinds, small_rig_cell

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(300)]


def _stored(n: int) -> Any:
    def ok(s: dict[str, Any]) -> bool:
        return (s.get("campaign") or {}).get("stored", 0) >= n

    return ok


def _ctrl_c(d: Any, timeout: float = 60) -> int:
    """SIGINT to the service's process group, as a terminal's Ctrl-C; its exit code."""
    os.killpg(d.proc.pid, signal.SIGINT)
    code = int(d.proc.wait(timeout))
    d.log.close()
    return code


def _log_after_the_signal(d: Any) -> list[str]:
    lines = (d.folder / "daemon.log").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if "SIGINT: stopping" in line)
    return lines[first:]


def _check_interrupted(d: Any, cid: int) -> None:
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0] == "interrupted"
    seen = kinds(d.db, cid)
    assert "interrupted" in seen and not FAULT_KINDS & set(seen), seen
    assert seen[-1] == "service-stopped"  # the next service holds it for a resume


def test_ctrl_c_on_the_tracker_service_is_sigint_and_an_interrupt(
    folder: Path, daemon: Any
) -> None:
    d = daemon(folder, None, time_scale=0.02, new_session=True)
    d.start()
    cid = call(d.sock, "POST", "/v1/campaigns", {})["campaign_id"]
    d.until(_stored(2))
    assert _ctrl_c(d) == 0, d.tail()
    after = _log_after_the_signal(d)
    text = "\n".join(after)
    assert "SIGTERM" not in text and "Traceback" not in text, text
    assert after[-1].endswith("cellcal.service: stopped"), text
    _check_interrupted(d, cid)


def test_ctrl_c_on_the_rig_service_stops_it_cleanly_and_a_restart_resumes(
    folder: Path, daemon: Any
) -> None:
    gige_or_skip()
    config = small_rig_cell(folder)
    d = daemon(folder, None, time_scale=0.0, config=config, new_session=True)
    d.start()
    cid = call(d.sock, "POST", "/v1/campaigns", {})["campaign_id"]
    d.until(_stored(1), 120)
    planned = d.rows(f"SELECT n_poses FROM campaigns WHERE id = {cid}")[0][0]
    assert _ctrl_c(d) == 0, d.tail()
    assert 0 < d.rows("SELECT COUNT(*) FROM poses")[0][0] < planned
    after = _log_after_the_signal(d)
    text = "\n".join(after)
    assert "KeyboardInterrupt" not in text and "Traceback" not in text, text
    assert "SIGTERM" not in text and "did not stop" not in text, text
    assert not [line for line in after if " WARNING " in line or " ERROR " in line], text
    assert after[-1].endswith("cellcal.service: stopped"), text  # nothing logged after it
    _check_interrupted(d, cid)

    d.start()  # held after the restart until an operator resumes it
    assert d.status()["paused_campaign"] == cid
    call(d.sock, "POST", f"/v1/campaigns/{cid}/resume", {})
    d.until(lambda s: s["state"] == "idle" and "complete" in s["reason"], 180)
    idx = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {cid}")]
    assert sorted(idx) == list(range(planned))  # every pose exactly once
    assert d.stop() == 0
