"""The cell service as a subprocess in mock mode (the bundled cell's tracker alone), driven
through its control API with the CLI's own client: start, pause (deferred and
immediate), resume, abort, a queue of two, SIGKILL and restart with every pose exactly
once, SIGTERM mid-dwell; a fake systemd sees READY, STATUS, WATCHDOG and STOPPING."""

from __future__ import annotations

import asyncio
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call
from cellcal.service.control import Control
from cellcal.service.daemon import _watchdog
from cellcal.service.sdnotify import Notifier
from tests.daemon.conftest import small_cell

ROOT = Path(__file__).resolve().parents[2]
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


class Collector(threading.Thread):
    """Reads the fake systemd's socket all along, as systemd does."""

    def __init__(self, systemd: Any) -> None:
        super().__init__(daemon=True)
        self.systemd = systemd
        self.seen: list[dict[str, str]] = []
        self.systemd.sock.settimeout(0.2)
        self.start()

    def run(self) -> None:
        while True:
            try:
                self.seen.append(self.systemd.receive()[0])
            except TimeoutError:
                continue
            except OSError:
                return

    def take(self) -> list[dict[str, str]]:
        time.sleep(0.3)  # what is under way arrives
        out, self.seen = self.seen, []
        return out


def running(n: int) -> Callable[[dict[str, Any]], bool]:
    def ok(s: dict[str, Any]) -> bool:
        c = s.get("campaign") or {}
        return s["state"] == "running" and c.get("stored", 0) >= n

    return ok


def test_start_pause_resume_abort_queue_sigkill_resume(
    folder: Path, fake: Any, daemon: Any
) -> None:
    systemd, notify_path = fake
    collector = Collector(systemd)
    d = daemon(folder, notify_path, time_scale=0.02, config=small_cell(folder))
    d.start()
    seen: dict[str, str] = {}
    for fields in collector.take():
        seen.update(fields)
    assert seen.get("READY") == "1"
    assert "STATUS" in seen and "devices" in seen["STATUS"]
    assert seen.get("WATCHDOG") == "1"  # the engine's heartbeat is fresh while idle

    first = call(d.sock, "POST", "/v1/campaigns", {"when": "now"})["campaign_id"]
    d.until(running(3))
    # A second campaign "now" while one runs is refused; queued, it waits.
    with pytest.raises(Exception, match="start with --queue"):
        call(d.sock, "POST", "/v1/campaigns", {"when": "now"})
    second = call(d.sock, "POST", "/v1/campaigns", {"when": "queue"})["campaign_id"]
    assert d.status()["queue"] == [second]

    # Deferred pause: the pose under way is finished and stored.
    assert call(d.sock, "POST", "/v1/campaigns/current/pause", {})["state"] == "pausing"
    s = d.until(lambda s: s["state"] == "paused")
    stored = s["campaign"]["stored"]
    assert d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {first}")[0][0] == stored
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {first}")[0][0] == "paused"
    time.sleep(0.5)  # nothing moves while paused, and the queue waits
    assert d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {first}")[0][0] == stored
    assert d.status()["queue"] == [second]

    # Resume, then pause at once: nothing half-measured is stored.
    call(d.sock, "POST", f"/v1/campaigns/{first}/resume", {})
    d.until(running(stored + 3))
    call(d.sock, "POST", "/v1/campaigns/current/pause", {"mode": "immediate"})
    s = d.until(lambda s: s["state"] == "paused")
    n = d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {first}")[0][0]
    assert n == s["campaign"]["stored"] > stored

    # Abort the paused campaign: the queued one starts.
    assert call(d.sock, "POST", "/v1/campaigns/current/abort", {})["state"] == "aborted"
    d.until(lambda s: s["state"] == "running" and s["campaign"]["id"] == second)
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {first}")[0][0] == "aborted"
    events = d.rows(f"SELECT kind, message FROM events WHERE campaign_id = {first}")
    operator = [m for k, m in events if k == "operator"]
    assert any(m.startswith(f"pause (deferred) by uid {os.getuid()}") for m in operator)
    assert any(m.startswith("abort by uid") for m in operator)

    # SIGKILL the service mid-campaign; the restarted one holds it until resumed.
    d.until(running(5))
    d.stop(signal.SIGKILL)
    d.start()
    s = d.status()
    assert s["state"] == "paused" and s["paused_campaign"] == second
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {second}")[0][0] == "interrupted"
    kinds = [k for (k,) in d.rows(f"SELECT kind FROM events WHERE campaign_id = {second}")]
    assert "recovered" in kinds
    before = d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {second}")[0][0]
    time.sleep(0.5)
    assert d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {second}")[0][0] == before
    call(d.sock, "POST", "/v1/campaigns/current/resume", {})
    d.until(lambda s: s["state"] == "idle" and "complete" in s["reason"], 180)
    planned, status = d.rows(f"SELECT n_poses, status FROM campaigns WHERE id = {second}")[0]
    assert status == "complete"
    idx = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {second}")]
    assert sorted(idx) == list(range(planned))  # every pose exactly once
    # The service wrote the complete campaign's report beside the database, and said so.
    report = folder / "reports" / f"campaign-{second}"
    assert f"report in {report}" in d.status()["reason"]
    assert "<svg" in (report / "index.html").read_text()
    assert not (folder / "reports" / f"campaign-{first}").exists()  # aborted: no report
    assert d.stop() == 0


def test_sigterm_mid_dwell_stops_within_seconds(folder: Path, fake: Any, daemon: Any) -> None:
    systemd, notify_path = fake
    collector = Collector(systemd)
    d = daemon(folder, notify_path, time_scale=1.0)  # a 7 s dwell in real time
    d.start()
    cid = call(d.sock, "POST", "/v1/campaigns", {})["campaign_id"]
    d.until(lambda s: (s.get("campaign") or {}).get("phase") == "dwell", 60)
    t0 = time.monotonic()
    assert d.stop(signal.SIGTERM) == 0
    assert time.monotonic() - t0 < 5.0
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0] == "interrupted"
    kinds = [k for (k,) in d.rows(f"SELECT kind FROM events WHERE campaign_id = {cid}")]
    assert kinds[-1] == "service-stopped"
    seen = collector.take()
    assert any(f.get("STOPPING") == "1" for f in seen)
    assert not Path(d.sock).exists()


def test_watchdog_pings_only_while_the_engine_beats(fake: Any) -> None:
    systemd, notify_path = fake
    collector = Collector(systemd)
    control = Control(["robot"], lambda kind, data: None)
    notifier = Notifier({"NOTIFY_SOCKET": notify_path})

    async def tick(seconds: float) -> None:
        task = asyncio.create_task(_watchdog(notifier, control, 0.05, 1.0))
        await asyncio.sleep(seconds)
        task.cancel()

    control.beat()
    asyncio.run(tick(0.2))
    assert {"WATCHDOG": "1"} in collector.take()
    control.heartbeat = time.monotonic() - 5.0  # a hung engine
    asyncio.run(tick(0.3))
    assert collector.take() == []
