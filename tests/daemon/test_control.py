"""The control object's way out: everything the engine sends waits in one outbox, the
loop is woken once for all that arrived since it last drained, in order, and a fast
engine's progress folds into one snapshot taken when the loop gets to it."""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcal.campaign.plan import PlannedPose
from cellcal.service.control import READY, Control


def _pose(idx: int) -> PlannedPose:
    return PlannedPose(
        idx, "calibration", "cube", np.array([650.0, -100.0, 900.0 + idx]), np.zeros(6)
    )


def test_one_wake_for_a_burst_in_order_with_one_snapshot() -> None:
    wakes: list[int] = []
    published: list[tuple[str, dict[str, Any]]] = []
    c = Control(
        ["robot", "tracker"], lambda k, d: published.append((k, d)), lambda: wakes.append(1)
    )
    for name in ("robot", "tracker"):
        c.set_device(name, READY)
    c.drain()
    wakes.clear()
    c.campaign = {"id": 7, "stored": 0, "planned": 3, "phase": "starting"}
    c.phase("move", _pose(0), 0.0)
    c._send("pose", {"idx": 0})
    c.phase("dwell", _pose(0), 1.0)
    c.phase("sample", _pose(0), 2.0)
    c._send("event", {"kind": "sensor-retry"})
    assert wakes == [1]  # one wake for the burst
    out = c.drain()
    assert [k for k, _ in out] == ["status", "pose", "event"]
    status = out[0][1]
    assert status["campaign"]["phase"] == "sample"  # the snapshot is taken at drain time
    assert status["campaign"]["target_mm"] == [650.0, -100.0, 900.0]
    assert c.drain() == [] and published == []
    c.phase("move", _pose(1), 3.0)
    assert wakes == [1, 1]
    (kind, snap), *_ = c.drain()
    assert kind == "status" and snap["campaign"]["pose_idx"] == 1
    assert snap["campaign"]["target_mm"][2] == 901.0  # a new pose: its numbers anew


def test_without_a_loop_each_item_goes_at_once() -> None:
    published: list[tuple[str, dict[str, Any]]] = []
    c = Control(["robot"], lambda k, d: published.append((k, d)))
    c.set_device("robot", READY)
    c.campaign = {"id": 1, "stored": 0, "planned": 1, "phase": "starting"}
    c.phase("move", _pose(0), 0.0)
    c.phase("dwell", _pose(0), 1.0)
    assert [k for k, _ in published][-2:] == ["status", "status"]
    assert published[-1][1]["campaign"]["phase"] == "dwell"


class _Loop:
    """What the flusher asks of the asyncio loop, recorded instead of run."""

    def __init__(self) -> None:
        self.soon: list[object] = []
        self.later: list[tuple[float, object]] = []

    def call_soon_threadsafe(self, fn: object) -> None:
        self.soon.append(fn)

    def call_later(self, delay: float, fn: object) -> None:
        self.later.append((delay, fn))


def test_the_flusher_sends_at_once_after_a_quiet_spell_then_in_batches() -> None:
    from cellcal.service.daemon import BATCH_S, Flusher

    outbox: list[tuple[str, dict[str, int]]] = []
    sent: list[tuple[str, dict[str, int]]] = []

    def drain() -> list[tuple[str, dict[str, int]]]:
        items = list(outbox)
        outbox.clear()
        return items

    loop = _Loop()
    flusher = Flusher(loop, drain, lambda kind, data: sent.append((kind, data)))  # type: ignore[arg-type]
    # Quiet: the first event wakes the loop at once.
    outbox.append(("pose", {"idx": 0}))
    flusher.wake()
    assert loop.soon == [flusher.flush] and not loop.later
    flusher.flush()
    assert sent == [("pose", {"idx": 0})]
    # Events keep coming: the loop looks again BATCH_S later and is not woken for each.
    assert loop.later == [(BATCH_S, flusher.flush)] and flusher.armed
    for k in (1, 2, 3):
        outbox.append(("pose", {"idx": k}))
        flusher.wake()
    assert len(loop.soon) == 1
    flusher.flush()  # the timer
    assert [d["idx"] for _, d in sent] == [0, 1, 2, 3]  # all of them, in order
    assert len(loop.later) == 2
    # Nothing more came: the next look finds nothing and stops looking.
    flusher.flush()
    assert not flusher.armed and len(loop.later) == 2
    outbox.append(("status", {"idx": 4}))
    flusher.wake()
    assert len(loop.soon) == 2  # quiet again: at once


def test_the_stop_names_its_signal() -> None:
    """A service stopped by Ctrl-C says SIGINT in its status, by systemd SIGTERM."""
    for name in ("SIGINT", "SIGTERM"):
        c = Control(["robot"], lambda k, d: None)
        c.shutdown(name)
        assert c.state == "stopping" and c.reason == f"stopping ({name})"
        assert c.intent == "interrupted"
