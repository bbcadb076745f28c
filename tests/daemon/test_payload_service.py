"""Payload sessions in the service: the campaign pauses before its second payload with
the instruction in its status, and ``cellcal campaign resume`` — the operator's word
that the payload is mounted — runs it to its end, every pose once."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.conftest import small_tracker_file
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


def test_the_service_pauses_for_the_next_payload_and_resumes(folder: Path, daemon: Any) -> None:
    cell = small_tracker_file(
        folder, "payloads", [2, 2, 2], 2, 4, campaign={"payloads_kg": [0.0, 2.0]}
    )
    d = daemon(folder, None, time_scale=0.002, config=cell)
    d.start()
    run = cellcal("campaign", "start", "--socket", d.sock, "--json")
    assert run.returncode == 0, run.stderr
    s = d.until(lambda s: s["state"] == "paused", 120)
    cid = s["campaign"]["id"]
    assert "12 of 24 poses stored; mount the 2 kg payload" in s["reason"]
    assert f"cellcal campaign resume {cid}" in s["reason"]
    run = cellcal("campaign", "status", "--socket", d.sock)
    assert "mount the 2 kg payload" in run.stdout

    run = cellcal("campaign", "resume", str(cid), "--socket", d.sock)
    assert run.returncode == 0, run.stderr
    d.until(lambda s: s["state"] == "idle" and "complete" in s["reason"], 120)
    idx = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {cid}")]
    assert sorted(idx) == list(range(24))
    said = d.rows(f"SELECT message FROM events WHERE campaign_id = {cid} AND kind = 'payload'")
    assert [m for (m,) in said] == [
        "0 kg payload on the robot",
        "2 kg payload mounted (the campaign resumed)",
    ]
    assert d.stop() == 0
