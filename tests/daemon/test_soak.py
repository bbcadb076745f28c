"""The soak, bounded: one mock campaign in the service (as a subprocess) through every
fault the cell knows — the tracker's beam broken every 15th series, its link dropped
after every 600 lines, a protective stop of the robot every 50th move, and a SIGKILL of
the service half-way — acted on as an operator would (resume whatever is paused). It
must end complete with every planned pose stored exactly once, every sample with it,
and it prints the faults it survived."""

from __future__ import annotations

import signal
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call

ROOT = Path(__file__).resolve().parents[2]
FAULTS = """
[simulation.faults]
tracker_beam_break_every = 15
tracker_beam_restore_s = 0.1
tracker_drop_after_lines = 600
robot_protective_stop_every = 50
"""

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(400)]


def test_soak_beam_breaks_dropped_links_protective_stops_and_a_sigkill(
    folder: Path, daemon: Callable[..., Any], capsys: pytest.CaptureFixture[str]
) -> None:
    config = folder / "soak.toml"
    config.write_text((ROOT / "config" / "mock-cell-tracker.toml").read_text() + FAULTS)
    d = daemon(folder, None, 0.01, config=config)
    d.start()
    started = call(d.sock, "POST", "/v1/campaigns", {"mock": True})
    cid, planned = started["campaign_id"], started["n_poses"]
    stops: Counter[str] = Counter()
    killed = False
    deadline = time.monotonic() + 330
    while True:
        assert time.monotonic() < deadline, f"soak did not end: {d.status()}\n{d.tail()}"
        status = d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0]
        if status == "complete":
            break
        assert status not in ("aborted", "refused"), d.tail()
        s = d.status()
        stored = d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {cid}")[0][0]
        if not killed and stored >= planned // 2 and s["state"] == "running":
            d.proc.send_signal(signal.SIGKILL)
            d.proc.wait(10)
            d.log.close()
            killed = True
            d.start()
            continue
        if s["state"] == "paused" and all(v["state"] == "ready" for v in s["devices"].values()):
            reason = s["reason"]
            stops["protective stop" if "e-stop" in reason else reason.split(":")[0]] += 1
            call(d.sock, "POST", f"/v1/campaigns/{cid}/resume", {})
            d.until(lambda s: s["state"] != "paused", 30)
        time.sleep(0.05)
    assert d.stop() == 0

    idx = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {cid} ORDER BY idx")]
    assert idx == list(range(planned)), "a pose lost or measured twice"
    per_pose = d.rows(
        f"""SELECT COUNT(*) FROM samples s JOIN poses p ON p.id = s.pose_id
        WHERE p.campaign_id = {cid} GROUP BY p.id"""
    )
    assert {n for (n,) in per_pose} == {20}, "every pose keeps its 20 samples"
    retried = d.rows(
        f"""SELECT COALESCE(SUM(s.retries), 0) FROM pose_stats s JOIN poses p
        ON p.id = s.pose_id WHERE p.campaign_id = {cid}"""
    )[0][0]
    kinds = Counter(k for (k,) in d.rows(f"SELECT kind FROM events WHERE campaign_id = {cid}"))
    assert killed and kinds["recovered"] == 1
    assert stops["protective stop"] >= 1, stops
    assert retried >= 3, "beam breaks and dropped links were retried"
    line = (
        f"soak survived: {retried} tracker series retried (beam breaks, dropped links), "
        f"{kinds['sensor-retry']} poses re-asked, {stops['protective stop']} protective stops "
        f"(paused, resumed), {sum(stops.values()) - stops['protective stop']} other pauses, "
        f"1 SIGKILL of the service; {planned} poses each stored once"
    )
    with capsys.disabled():
        print(f"\n  {line}")
