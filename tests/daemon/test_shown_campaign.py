"""One campaign at a time in the status (API, event stream, status page): the running
one, else the one held, else the last one — and every pose it lists is that campaign's.
The control object on its own, then the service as a subprocess (the tracker-only mock
cell): campaign A then B; a held campaign across restarts (SIGTERM, SIGKILL). And one σ
for the page and ``cellcal campaign watch``."""

from __future__ import annotations

import http.client
import json
import random
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from cellcal.campaign.plan import Plan, PlannedPose
from cellcal.campaign.records import CampaignStarted, PoseStored
from cellcal.commands.campaign import _show, campaign
from cellcal.commands.service_client import call, follow
from cellcal.drivers.base import Series
from cellcal.service.control import READY, Control, event_data
from tests.daemon.conftest import small_cell

ROOT = Path(__file__).resolve().parents[2]
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


# ---------------------------------------------------------------- the control object


def _pose(idx: int) -> PlannedPose:
    return PlannedPose(
        idx, "calibration", "cube", np.array([650.0, -100.0, 900.0 + idx]), np.zeros(6)
    )


def _started(cid: int, done: int, total: int = 10) -> CampaignStarted:
    plan = Plan(tuple(_pose(i) for i in range(total)), ())
    return CampaignStarted(cid, plan, "digest", done, done > 0, 0.0)


def _stored(cid: int, idx: int, done: int, total: int = 10) -> PoseStored:
    """A pose whose samples spread about 20 µm along each axis."""
    rng = np.random.default_rng(idx)
    xyz = rng.normal(0.0, 0.02, (20, 3)) + np.array([1000.0, 0.0, 500.0])
    t = 0.1 * np.arange(20)
    return PoseStored(
        cid, _pose(idx), np.zeros(6), (Series("tracker", t, t, xyz),), 0, 7, 0, done, total
    )


def _control() -> tuple[Control, list[tuple[str, dict[str, Any]]]]:
    published: list[tuple[str, dict[str, Any]]] = []
    c = Control(["robot", "tracker"], lambda k, d: published.append((k, d)))
    for name in ("robot", "tracker"):
        c.set_device(name, READY)
    return c, published


def test_a_campaign_that_starts_is_shown_without_the_last_ones_poses() -> None:
    c, published = _control()
    c.next_job(lambda: 1)
    c.record(_started(1, 0))
    for i in range(5):
        c.record(_stored(1, i, i + 1))
    c.finished(1, "complete", "complete")
    snap = c.snapshot(recent=True)
    assert len(snap["recent_poses"]) == 5
    published.clear()
    c.next_job(lambda: 2)
    c.record(_started(2, 0))
    # the stream says at once which campaign is shown, and that it has no pose yet
    switch = [d for k, d in published if k == "status" and "recent_poses" in d]
    assert [(d["campaign"]["id"], d["recent_poses"]) for d in switch] == [(2, [])]
    c.record(_stored(2, 0, 1))
    snap = c.snapshot(recent=True)
    assert [(p["campaign_id"], p["idx"]) for p in snap["recent_poses"]] == [(2, 0)]
    assert snap["campaign"]["id"] == 2 and snap["campaign"].get("status") == "running"


def test_a_resumed_campaign_shows_the_poses_it_stored_before() -> None:
    """Campaign 4, interrupted with 3 poses stored, resumed while campaign 1 is shown:
    its poses are read from the database (the service's loader)."""
    c, _ = _control()
    c.next_job(lambda: 1)
    c.record(_started(1, 0))
    c.record(_stored(1, 0, 1))
    c.finished(1, "complete", "complete")
    asked: list[int] = []

    def history(cid: int) -> list[dict[str, Any]]:
        asked.append(cid)
        return [event_data(_stored(cid, i, i + 1)) for i in range(3)]

    c.history = history
    c.resume(4, lambda cid: "interrupted")
    c.next_job(lambda: None)
    c.record(_started(4, 3))
    c.record(_stored(4, 3, 4))
    snap = c.snapshot(recent=True)
    assert asked == [4]
    assert snap["campaign"]["id"] == 4 and snap["campaign"]["stored"] == 4
    assert [(p["campaign_id"], p["idx"]) for p in snap["recent_poses"]] == [
        (4, i) for i in range(4)
    ]
    # resumed again in this process: the poses it has are kept, nothing read again
    c.finished(4, "paused", "paused after 4 poses")
    c.resume(4, lambda cid: "paused")
    c.next_job(lambda: None)
    c.record(_started(4, 4))
    assert asked == [4] and len(c.snapshot(recent=True)["recent_poses"]) == 4


def test_the_page_and_campaign_watch_show_one_sigma(capsys: pytest.CaptureFixture[str]) -> None:
    """σ is the 3-D norm of the per-axis standard deviations, sent by the service (the
    page plots it in µm) and printed by ``cellcal campaign watch`` (mm) — not the largest
    axis."""
    data = event_data(_stored(1, 0, 1))
    s = data["sensors"]["tracker"]
    std = np.asarray(s["std_mm"])
    assert s["sigma_mm"] == pytest.approx(float(np.linalg.norm(std)), abs=1e-4)
    assert s["sigma_mm"] > max(std) + 0.005
    _show("pose", data)
    assert f"tracker 3-D σ {s['sigma_mm']:.4f} mm" in capsys.readouterr().out


# ---------------------------------------------------------------- the service


def _short_campaign() -> str:
    """The tracker cell with a smaller plan (its [robot] and [sensor] unchanged)."""
    text = TRACKER_CELL.read_text()
    text = text.replace("grid = [4, 4, 5]", "grid = [3, 3, 4]")
    text = text.replace("validation_inside = 20", "validation_inside = 8")
    return text.replace("validation_per_region = 6", "validation_per_region = 2")


def _start(d: Any, body: dict[str, Any] | None = None) -> int:
    body = body or {"config_toml": _short_campaign(), "config_name": str(TRACKER_CELL)}
    cid = call(d.sock, "POST", "/v1/campaigns", body)["campaign_id"]
    assert isinstance(cid, int)
    return cid


def _idx(d: Any, cid: int) -> list[int]:
    """The campaign's stored poses, in the order stored."""
    return [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {cid} ORDER BY id")]


def _stored_at_least(n: int) -> Callable[[dict[str, Any]], bool]:
    def ok(s: dict[str, Any]) -> bool:
        return s["state"] == "running" and (s["campaign"] or {}).get("stored", 0) >= n

    return ok


def _page_status(d: Any) -> dict[str, Any]:
    """``/v1/status`` from the status page's site."""
    url = call(d.sock, "GET", "/v1/info")["http"]
    host, port = url.removeprefix("http://").rstrip("/").rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port), timeout=10)
    conn.request("GET", "/v1/status", headers={"Host": f"{host}:{port}"})
    resp = conn.getresponse()
    data = json.loads(resp.read())
    conn.close()
    assert resp.status == 200
    assert isinstance(data, dict)
    return data


class Watcher(threading.Thread):
    """The event stream read as the page reads it, until ``until`` says so."""

    def __init__(self, sock: str, until: Callable[[str, dict[str, Any]], bool]) -> None:
        super().__init__(daemon=True)
        self.sock, self.until = sock, until
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.connected = threading.Event()
        self.start()

    def run(self) -> None:
        def handle(_: int, kind: str, data: dict[str, Any]) -> bool:
            self.events.append((kind, data))
            self.connected.set()
            return self.until(kind, data)

        follow(self.sock, handle)


def _check_shown(s: dict[str, Any], cid: int, status: str, stored: list[int]) -> None:
    """The status shows campaign ``cid`` with its last poses, those stored, and no other."""
    recent = s["recent_poses"]
    assert {p["campaign_id"] for p in recent} == {cid}
    assert [p["idx"] for p in recent] == stored[-30:]
    c = s["campaign"]
    assert c is not None, s
    assert (c["id"], c.get("status"), c["stored"]) == (cid, status, len(stored)), c
    for p in recent:
        sensor = p["sensors"]["tracker"]
        assert sensor["sigma_mm"] == pytest.approx(np.linalg.norm(sensor["std_mm"]), abs=2e-4)


def test_campaign_b_is_shown_with_its_poses_alone(folder: Path, daemon: Callable[..., Any]) -> None:
    address = f"127.0.0.{random.randint(2, 254)}"
    d = daemon(folder, None, 0.02, ["--http", f"{address}:0"], config=small_cell(folder))
    d.start()
    a = _start(d)
    done = d.until(lambda s: s["state"] == "idle" and f"campaign {a} complete" in s["reason"], 120)
    stored_a = _idx(d, a)

    # Watch the stream from before B starts until B has stored 3 poses.
    def b_has_three(kind: str, data: dict[str, Any]) -> bool:
        return kind == "pose" and data["campaign_id"] != a and data["stored"] >= 3

    watcher = Watcher(d.sock, b_has_three)
    assert watcher.connected.wait(30)
    b = _start(d)
    watcher.join(60)
    assert not watcher.is_alive()

    # Paused: the API, and the page's own /v1/status, show B and its poses only.
    call(d.sock, "POST", "/v1/campaigns/current/pause", {})
    d.until(lambda s: s["state"] == "paused")
    for s in (d.status(), _page_status(d)):
        _check_shown(s, b, "paused", _idx(d, b))
        assert s["paused_campaign"] == b
    # The stream: A shown until B started, then B (with none of A's poses), and B's poses.
    assert watcher.events[0][0] == "status"
    _check_shown(watcher.events[0][1], a, "complete", stored_a)
    assert done["last_end"]["campaign_id"] == a
    switch = [
        data
        for kind, data in watcher.events
        if kind == "status" and data["campaign"]["id"] == b and "recent_poses" in data
    ]
    assert switch and switch[0]["recent_poses"] == []
    poses = [data for kind, data in watcher.events if kind == "pose"]
    assert poses and {p["campaign_id"] for p in poses} == {b}
    # A new watcher's first status is B's too.
    first = Watcher(d.sock, lambda kind, data: True)
    first.join(30)
    assert first.events[0][0] == "status"
    _check_shown(first.events[0][1], b, "paused", _idx(d, b))

    # Aborted, B is still the campaign shown (the last one), until another starts.
    call(d.sock, "POST", "/v1/campaigns/current/abort", {})
    _check_shown(d.until(lambda s: s["state"] == "idle"), b, "aborted", _idx(d, b))
    assert d.stop() == 0


def test_a_held_campaign_is_reported_after_restarts(
    folder: Path, daemon: Callable[..., Any]
) -> None:
    d = daemon(folder, None, 0.02, config=small_cell(folder))
    d.start()
    cid = _start(d, {"when": "now"})
    planned = d.rows(f"SELECT n_poses FROM campaigns WHERE id = {cid}")[0][0]
    d.until(_stored_at_least(5))
    call(d.sock, "POST", "/v1/campaigns/current/pause", {})
    d.until(lambda s: s["state"] == "paused")
    stored = _idx(d, cid)

    def held(s: dict[str, Any]) -> None:
        assert s["state"] == "paused" and s["paused_campaign"] == cid
        _check_shown(s, cid, "interrupted", stored)
        assert s["campaign"]["planned"] == planned
        assert s["campaign"]["reached_idx"] == stored[-1]
        assert f"cellcal campaign resume {cid}" in s["reason"]

    # Paused, then the service stopped (SIGTERM) and started on the same database.
    assert d.stop() == 0
    d.start()
    held(d.status())
    out = CliRunner().invoke(campaign, ["status", "--socket", d.sock]).output
    assert f"campaign {cid} (interrupted): {len(stored)} of {planned} poses stored" in out
    assert f"cellcal campaign resume {cid}" in out

    # Stopped again without a resume: still held, still reported.
    assert d.stop() == 0
    d.start()
    held(d.status())

    # Resumed: the poses stored before the restarts stay in the list, new ones follow.
    call(d.sock, "POST", "/v1/campaigns/current/resume", {})
    d.until(_stored_at_least(len(stored) + 3))
    call(d.sock, "POST", "/v1/campaigns/current/pause", {})
    d.until(lambda s: s["state"] == "paused")
    stored = _idx(d, cid)
    _check_shown(d.status(), cid, "paused", stored)

    # Killed while it runs: found running, held and reported with every pose it stored.
    call(d.sock, "POST", "/v1/campaigns/current/resume", {})
    d.until(_stored_at_least(len(stored) + 2))
    d.stop(signal.SIGKILL)
    stored = _idx(d, cid)
    d.start()
    held(d.status())
    assert d.stop() == 0
