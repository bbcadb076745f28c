"""A campaign that cannot start ends; it never traps the engine in a loop (issue 29).

A queued campaign whose stored configuration cannot be read back (a seed above 2³²−1,
queued by a service that did not bound it) was taken from the queue, failed, stayed
queued and was taken again: 1 450 log lines a second, the queue blocked, an abort
answered and changed nothing, a restart went on with it. Now a start that fails for a
reason that will not change ends the campaign ``failed`` with the reason; an abort
asked while it starts ends it ``aborted``; a device that fails before the start holds
it ``paused`` (the devices may come back: an operator resumes it); a restart finds
nothing to run again."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from cellcal.campaign.runner import plan_campaign, queue_campaign
from cellcal.clock import SimulatedClock
from cellcal.config import CellConfig, load_config
from cellcal.errors import DeviceError
from cellcal.files.models import load_model
from cellcal.service.control import READY, Control
from cellcal.service.worker import Worker, device_names, oldest_queued
from cellcal.store.database import Store
from tests.daemon.conftest import small_cell

pytestmark = pytest.mark.timeout(120)

BAD_SEED = 2**40  # what the unbounded API let through


def _queue(db: Path, config: CellConfig) -> int:
    store = Store(str(db))
    try:
        plan, _ = plan_campaign(config)
        return queue_campaign(store, config, plan, config_path=None, mock=True, time_scale=0.0)
    finally:
        store.close()


def _set_seed(db: Path, cid: int, seed: int) -> None:
    """The stored configuration's seed set behind the configuration's back, as the
    service that did not bound it stored it."""
    with sqlite3.connect(db) as conn:
        (text,) = conn.execute("SELECT config_json FROM campaigns WHERE id = ?", (cid,)).fetchone()
        stored = json.loads(text)
        stored["campaign"]["seed"] = seed
        conn.execute("UPDATE campaigns SET config_json = ? WHERE id = ?", (json.dumps(stored), cid))


class Engine:
    """The service's engine thread's parts, run in the test's thread: the control
    object, a worker on stand-in devices, the database."""

    def __init__(self, db: Path, config: CellConfig, devices: Any = None) -> None:
        self.published: list[tuple[str, dict[str, Any]]] = []
        self.control = Control(device_names(config), lambda k, d: self.published.append((k, d)))
        for name in device_names(config):
            self.control.set_device(name, READY)
        nominal = load_model(config.robot.model).model
        self.worker = Worker(self.control, config, nominal, str(db), SimulatedClock(0.0), mock=True)
        stand_in: Any = devices if devices is not None else SimpleNamespace(sensors=())
        self.worker.devices = stand_in
        self.store = Store(str(db))

    def next(self) -> int | None:
        """The campaign the engine takes next; None: nothing (one look, not a wait)."""
        looks: list[int] = []

        def looked_once() -> bool:
            looks.append(1)
            return len(looks) > 1

        job = self.control.next_job(lambda: oldest_queued(self.store), looked_once, 0.01)
        return None if job is None else job.campaign_id

    def run(self, cid: int) -> None:
        from cellcal.service.control import Job

        self.worker._run(self.store, Job(cid, resume=False))

    def events(self, cid: int) -> list[tuple[str, str]]:
        return [(e["kind"], e["message"]) for e in self.store.events(cid)]


@pytest.fixture
def config(tmp_path: Path) -> CellConfig:
    return load_config(small_cell(tmp_path))


def test_a_campaign_that_cannot_start_ends_failed_and_the_queue_goes_on(
    tmp_path: Path, config: CellConfig
) -> None:
    db = tmp_path / "c.db"
    bad = _queue(db, config)
    _set_seed(db, bad, BAD_SEED)
    good = _queue(db, config)
    engine = Engine(db, config)
    assert engine.next() == bad
    engine.run(bad)
    assert engine.store.campaign(bad).status == "failed"
    kinds = engine.events(bad)
    assert any(k == "error" and "seed" in m for k, m in kinds), kinds
    assert engine.control.state == "idle"
    assert f"campaign {bad} failed" in engine.control.reason
    ends = [d for k, d in engine.published if k == "campaign-end"]
    assert ends and ends[-1]["campaign_id"] == bad and ends[-1]["status"] == "failed"
    # the queue goes on with the next one; the failed one is never taken again
    assert engine.next() == good


def test_an_abort_while_it_starts_ends_it_aborted(tmp_path: Path, config: CellConfig) -> None:
    db = tmp_path / "c.db"
    bad = _queue(db, config)
    _set_seed(db, bad, BAD_SEED)
    engine = Engine(db, config)
    assert engine.next() == bad
    state, cid = engine.control.abort(None, lambda c: engine.store.campaign(c).status)
    assert (state, cid) == ("aborting", bad)
    engine.run(bad)
    assert engine.store.campaign(bad).status == "aborted"
    assert engine.control.state == "idle"
    assert engine.next() is None


def test_a_device_failing_before_the_start_holds_it_paused(
    tmp_path: Path, config: CellConfig
) -> None:
    """A device may come back: the campaign waits for an operator, and is not taken
    again and again meanwhile."""

    def describe() -> str:
        raise DeviceError("tracker: no answer to the identity request")

    sensor = SimpleNamespace(sensor=SimpleNamespace(describe=describe))
    db = tmp_path / "c.db"
    cid = _queue(db, config)
    engine = Engine(db, config, SimpleNamespace(sensors=(sensor,)))
    assert engine.next() == cid
    engine.run(cid)
    assert engine.store.campaign(cid).status == "paused"
    assert engine.control.blocking == cid
    assert engine.next() is None  # held: nothing runs until an operator resumes it


def test_the_service_ends_it_once_and_a_restart_leaves_it(
    folder: Path, daemon: Callable[..., Any]
) -> None:
    """The service as a subprocess on a database that holds such a campaign: it ends
    ``failed`` at the first attempt, the campaign queued behind it runs, and a restart
    does not take it up again."""
    cell = small_cell(folder)
    config = load_config(cell)
    bad = _queue(folder / "c.db", config)
    _set_seed(folder / "c.db", bad, BAD_SEED)
    d = daemon(folder, None, 0.0, config=cell)
    d.start()
    d.until(lambda s: (s.get("campaign") or {}).get("status") == "failed", 30)
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {bad}") == [("failed",)]
    assert d.stop() == 0
    log = (folder / "daemon.log").read_text()
    attempts = log.count(f"campaign {bad}: starting")
    assert attempts == 1, log[-3000:]
    d2 = daemon(folder, None, 0.0, config=cell)
    d2.start()
    snap = d2.until(lambda s: s["state"] == "idle")
    assert snap["queue"] == []
    assert d2.stop() == 0
    log = (folder / "daemon.log").read_text()
    assert log.count(f"campaign {bad}: starting") == 1, log[-3000:]
