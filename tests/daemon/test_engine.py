"""The engine on a simulated clock: time as planned, no wall time, stop and resume.

The second sensor, "rig", is an in-process test double that spends its sampling time on
the clock (the engine treats every sensor alike; the rig's own path, rendered images
through GigE Vision twins, is tested in tests/e2e and tests/drivers)."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest

from cellcal.campaign.devices import build_devices
from cellcal.campaign.engine import SensorSetting, acquire
from cellcal.campaign.plan import make_plan
from cellcal.campaign.records import CampaignEvent, PoseStored, RecordStream
from cellcal.campaign.store_writer import StoreWriter
from cellcal.clock import SimulatedClock
from cellcal.config import config_from_dict
from cellcal.drivers.base import Series
from cellcal.errors import DeviceError, NoTargetError
from cellcal.files.models import load_model
from cellcal.store.database import Store, StoreError

pytestmark = [pytest.mark.twin, pytest.mark.slow]

CONFIG = config_from_dict(
    {
        "sensor": [
            {
                "name": "tracker",
                "kind": "laser-tracker",
                "reference": True,
                "target_offset_mm": [25, -40, 130],
            },
            {"name": "rig", "kind": "laser-tracker", "target_offset_mm": [-30, 45, 120]},
        ],
        "campaign": {"grid": [2, 2, 2], "validation_inside": 2, "validation_per_region": 0},
    }
)
MODEL = load_model("kuka-kr5-arc").model


class PacedSensor:
    """n samples of the simulated truth with 0.05 mm noise, n / rate seconds on the clock."""

    def __init__(self, cell, clock, name):
        self.cell, self.clock, self.name = cell, clock, name
        self.rng = np.random.default_rng(11)

    def connect(self):
        self.rng = np.random.default_rng(11)

    def measure(self, n, rate_hz):
        t0 = self.clock.now()
        xyz = self.cell.true_position(self.name) + 0.05 * self.rng.normal(size=(n, 3))
        self.clock.sleep(n / rate_hz)
        t = t0 + np.arange(n) / rate_hz
        return Series(self.name, t, t + 1111.0, xyz)

    def close(self):
        self.rng = np.random.default_rng(11)


def _setup(tmp_path, clock):
    plan = make_plan(
        CONFIG.campaign, MODEL, np.radians(CONFIG.robot.home_deg), np.array([25.0, -40.0, 130.0])
    )
    devices = build_devices(CONFIG, MODEL, clock, mock=True, seed=3)
    paced = PacedSensor(devices.simulated_cell, clock, "rig")
    sensors = tuple(
        SensorSetting(paced, s.rate_hz) if s.sensor.name == "rig" else s for s in devices.sensors
    )
    devices.sensors[1].sensor.close()
    devices = dataclasses.replace(devices, sensors=sensors)
    store = Store(tmp_path / "c.db")
    cid = store.create_campaign(
        config_json=CONFIG.model_dump_json(),
        config_path=None,
        mock=True,
        seed=3,
        time_scale=0.0,
        model="kuka-kr5-arc",
        sensors=["tracker", "rig"],
        n_poses=len(plan.poses),
        samples_per_pose=20,
        dwell_s=7.0,
        plan_digest=plan.digest,
    )
    return plan, devices, store, cid


def _acquire(store, cid, plan, devices, clock, *, subscribers=(), **kw):
    stream = RecordStream()
    stream.subscribe(StoreWriter(store), critical=True)
    for s in subscribers:
        stream.subscribe(s)
    return acquire(
        plan,
        devices.robot,
        devices.sensors,
        clock,
        campaign_id=cid,
        done=store.completed_indices(cid),
        stream=stream,
        dwell_s=kw.pop("dwell_s", 7.0),
        samples_per_pose=20,
        speed=0.25,
        **kw,
    )


def test_simulated_clock_sleeps_overlap_and_cost_no_wall_time():
    clock = SimulatedClock()
    wall = time.monotonic()
    clock.sleep(7.0)
    assert clock.now() == 7.0

    def measure():
        with clock.branch(7.0):
            clock.sleep(2.0)

    threads = [threading.Thread(target=measure) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert clock.now() == pytest.approx(9.0)  # side by side: 2 s, not 4
    assert time.monotonic() - wall < 1.0  # and no real seven seconds


def test_a_pose_takes_dwell_plus_sampling_on_the_clock(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    out = _acquire(store, cid, plan, devices, clock)
    assert out.stored == out.stored_now == len(plan.poses) == 10
    rows = store.conn.execute("SELECT t_start, t_end FROM poses ORDER BY idx").fetchall()
    for t_start, t_end in rows:
        # move (≥ 0.5 s settle) + 7 s dwell + 20 samples at 10 Hz from both sensors at once (2 s)
        assert t_end - t_start >= 7.0 + 2.0 + 0.5
        assert t_end - t_start < 7.0 + 2.0 + 0.5 + 30.0
    # Both sensors start sampling together, after the dwell, on the host clock.
    both = dict(
        store.conn.execute(
            "SELECT sensor, MIN(host_time) FROM samples WHERE pose_id = 3 GROUP BY sensor"
        ).fetchall()
    )
    assert both["rig"] == pytest.approx(both["tracker"])
    assert out.clock_seconds >= 10 * 9.5
    n = store.conn.execute("SELECT sensor, COUNT(*) FROM samples GROUP BY sensor").fetchall()
    assert dict(n) == {"rig": 200, "tracker": 200}

    def times(sensor):
        return np.array(
            store.conn.execute(
                "SELECT host_time, device_time FROM samples WHERE sensor = ? AND pose_id = 1",
                (sensor,),
            ).fetchall()
        )

    # The tracker (real driver over TCP to the mock) stamps 10 Hz on its own clock and
    # the receipt on the host's; the in-process rig spends its 2 s on the host clock.
    tracker, rig = times("tracker"), times("rig")
    np.testing.assert_allclose(np.diff(tracker[:, 1]), 0.1, atol=1e-6)
    np.testing.assert_allclose(np.diff(rig[:, 0]), 0.1)
    assert (np.diff(tracker[:, 0]) >= 0).all()


def test_stop_leaves_a_resumable_campaign(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    stop = threading.Event()

    def stop_after_4(record):
        if isinstance(record, PoseStored) and record.done == 4:
            stop.set()

    out = _acquire(store, cid, plan, devices, clock, stop=stop, subscribers=[stop_after_4])
    assert out.interrupted and out.stored == 4
    assert store.completed_indices(cid) == {0, 1, 2, 3}
    again = _acquire(store, cid, plan, devices, clock)
    assert not again.interrupted and again.stored_now == 6 and again.stored == 10
    assert store.completed_indices(cid) == set(range(10))


def test_a_device_fault_propagates_and_keeps_what_was_stored(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    calls = {"n": 0}
    original = devices.robot.move_joints

    def flaky(q, speed):
        calls["n"] += 1
        if calls["n"] == 3:
            raise DeviceError("robot: protective stop")
        original(q, speed)

    devices.robot.move_joints = flaky
    with pytest.raises(DeviceError, match="protective stop"):
        _acquire(store, cid, plan, devices, clock)
    assert store.completed_indices(cid) == {0, 1}


def _rig_fails_once(devices, on_call: int, message: str, error=DeviceError) -> None:
    """The rig's ``on_call``-th measurement raises ``message``; every other one measures."""
    rig = next(s.sensor for s in devices.sensors if s.sensor.name == "rig")
    original = rig.measure
    calls = {"n": 0}

    def flaky(n, rate):
        calls["n"] += 1
        if calls["n"] == on_call:
            raise error(message)
        return original(n, rate)

    rig.measure = flaky


def test_a_failing_sensor_is_asked_again_and_the_event_kept(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    _rig_fails_once(devices, 4, "rig: camera 2 timed out")
    out = _acquire(store, cid, plan, devices, clock)
    assert out.stored == 10
    events = store.events(cid)
    assert [(e["kind"], e["pose_idx"]) for e in events] == [("sensor-retry", 3)]
    devices.close()


def _rig_fails_after_stop(devices, stop, on_call: int) -> dict[str, int]:
    """From its ``on_call``-th measurement the rig fails, as cameras whose process a
    Ctrl-C ended would, and the stop request comes at the same time; its calls."""
    rig = next(s.sensor for s in devices.sensors if s.sensor.name == "rig")
    original = rig.measure
    calls = {"n": 0}

    def failing(n, rate):
        calls["n"] += 1
        if calls["n"] >= on_call:
            stop.set()
            raise DeviceError("rig: no camera gave a frame")
        return original(n, rate)

    rig.measure = failing
    return calls


def test_a_sensor_failing_once_a_stop_was_asked_is_an_interrupt_not_a_device_fault(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    stop = threading.Event()
    calls = _rig_fails_after_stop(devices, stop, 4)
    out = _acquire(store, cid, plan, devices, clock, stop=stop)
    assert out.interrupted and out.stored == 3  # the pose under way abandoned, unstored
    assert calls["n"] == 4  # not measured again: the operator asked to stop
    assert store.events(cid) == []  # neither a sensor-retry nor a device-error
    assert store.completed_indices(cid) == {0, 1, 2}
    devices.close()


def test_a_move_failing_once_a_stop_was_asked_is_an_interrupt(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    stop = threading.Event()
    original = devices.robot.move_joints
    calls = {"n": 0}

    def flaky(q, speed):
        calls["n"] += 1
        if calls["n"] == 3:
            stop.set()
            raise DeviceError("robot: connection reset")
        original(q, speed)

    devices.robot.move_joints = flaky
    out = _acquire(store, cid, plan, devices, clock, stop=stop)
    assert out.interrupted and out.stored == 2
    assert store.events(cid) == []
    devices.close()


def test_a_sensor_that_does_not_see_its_target_leaves_the_pose_to_the_others(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    _rig_fails_once(devices, 4, "rig: the target is out of view", NoTargetError)
    out = _acquire(store, cid, plan, devices, clock)
    assert out.stored == 10  # no pose lost, none measured again
    events = store.events(cid)
    assert [(e["kind"], e["pose_idx"]) for e in events] == [("no-target", 3)]
    assert "kept without rig: rig: the target is out of view" in events[0]["message"]
    data = store.pose_data(cid)
    assert data.measured("tracker").all()
    assert data.measured("rig").tolist() == [k != 3 for k in range(10)]
    devices.close()


def test_a_short_series_is_stored_with_what_it_has_and_an_event_that_says_why(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    rig = next(s.sensor for s in devices.sensors if s.sensor.name == "rig")
    original = rig.measure
    calls = {"n": 0}

    def retaking(n, rate):
        calls["n"] += 1
        s = original(n, rate)
        if calls["n"] == 2:  # re-takes ran out: 18 of 20
            keep = slice(0, n - 2)
            why = "18 of 20 samples after 40 sets (22 sets missed the target): set 0: …"
            return Series(s.sensor, s.host_time[keep], s.device_time[keep], s.xyz[keep], note=why)
        if calls["n"] == 5:  # complete, with trouble on the way
            return dataclasses.replace(s, note="20 of 20 samples after 21 sets (1 set …)")
        return s

    rig.measure = retaking
    out = _acquire(store, cid, plan, devices, clock)
    assert out.stored == 10
    events = [(e["kind"], e["pose_idx"], e["message"]) for e in store.events(cid)]
    assert events == [
        ("short-series", 1, "pose 1, rig: 18 of 20 samples after 40 sets (22 sets missed the "
         "target): set 0: …"),
        ("sensor-note", 4, "pose 4, rig: 20 of 20 samples after 21 sets (1 set …)"),
    ]  # fmt: skip
    counts = dict(
        store.conn.execute(
            "SELECT p.idx, COUNT(*) FROM samples s JOIN poses p ON s.pose_id = p.id "
            "WHERE s.sensor = 'rig' GROUP BY p.idx"
        ).fetchall()
    )
    assert counts == {k: 18 if k == 1 else 20 for k in range(10)}
    devices.close()


def test_every_pose_and_event_is_a_record_and_a_failing_watcher_stops_nothing(tmp_path):
    clock = SimulatedClock()
    plan, devices, store, cid = _setup(tmp_path, clock)
    _rig_fails_once(devices, 2, "rig: camera 1 timed out")
    seen = []

    def broken(record):
        if isinstance(record, PoseStored) and record.done == 3:
            raise RuntimeError("the watcher's socket went away")
        seen.append(("broken", record))

    out = _acquire(
        store, cid, plan, devices, clock, subscribers=[lambda r: seen.append(("ok", r)), broken]
    )
    assert out.stored == 10 and store.completed_indices(cid) == set(range(10))
    ok = [r for who, r in seen if who == "ok"]
    poses = [r for r in ok if isinstance(r, PoseStored)]
    assert [r.done for r in poses] == list(range(1, 11)) and poses[0].total == 10
    assert [r.pose.idx for r in poses] == [p.idx for p in plan.poses]
    # The pose records are what the store kept: the same means, to the last bit.
    row = store.conn.execute(
        "SELECT AVG(x), AVG(y), AVG(z) FROM samples s JOIN poses p ON s.pose_id = p.id "
        "WHERE p.idx = ? AND s.sensor = 'tracker'",
        (poses[4].pose.idx,),
    ).fetchone()
    stats = {st.sensor: st for st in poses[4].statistics}
    np.testing.assert_allclose(row, stats["tracker"].mean, rtol=0, atol=1e-9)
    assert stats["tracker"].n == 20 and (stats["tracker"].std > 0).all()
    retry = [r for r in ok if isinstance(r, CampaignEvent)]
    assert [(e.kind, e.pose_idx) for e in retry] == [("sensor-retry", plan.poses[1].idx)]
    assert poses[1].retries == 1 and poses[0].retries == 0
    # The broken watcher saw the first two poses, then was dropped; nothing else noticed.
    assert len([r for who, r in seen if who == "broken" and isinstance(r, PoseStored)]) == 2
    devices.close()


def test_a_store_that_cannot_write_ends_the_acquisition(tmp_path):
    clock = SimulatedClock()
    plan, devices, _store, cid = _setup(tmp_path, clock)
    stream = RecordStream()
    written = []

    def full_disk(record):
        if isinstance(record, PoseStored):
            if len(written) == 2:
                raise StoreError("database or disk is full")
            written.append(record.pose.idx)

    stream.subscribe(full_disk, critical=True)
    watcher = []
    stream.subscribe(watcher.append)
    with pytest.raises(StoreError, match="disk is full"):
        acquire(
            plan, devices.robot, devices.sensors, clock, campaign_id=cid, done=set(),
            stream=stream, dwell_s=7.0, samples_per_pose=5, speed=0.25,
        )  # fmt: skip
    assert len(written) == 2 and len(watcher) == 3  # the watcher saw the third all the same
    devices.close()


@pytest.mark.timeout(60)
def test_a_stop_request_cuts_the_dwell_short(tmp_path):
    """With time paced (time_scale 1: a 7 s dwell is 7 wall seconds), a stop request
    during the dwell ends the acquisition at once, the pose unstored."""
    clock = SimulatedClock(time_scale=1.0)
    plan, devices, store, cid = _setup(tmp_path, clock)
    stop = threading.Event()
    timer = threading.Timer(0.3, stop.set)
    timer.start()
    wall = time.monotonic()
    out = _acquire(store, cid, plan, devices, clock, stop=stop, dwell_s=7.0)
    took = time.monotonic() - wall
    timer.join()
    assert out.interrupted and out.stored == 0 and store.completed_indices(cid) == set()
    assert took < 5.0  # not the 7 s of the dwell
    devices.close()


def test_simulated_clock_wait_is_cut_by_the_event_and_advances_by_what_was_waited():
    clock = SimulatedClock(time_scale=0.01)
    ev = threading.Event()
    assert clock.wait(ev, 2.0) is False and clock.now() == pytest.approx(2.0)
    ev.set()
    assert clock.wait(ev, 5.0) is True and clock.now() == pytest.approx(2.0)
    ev.clear()
    threading.Timer(0.02, ev.set).start()  # 2 simulated seconds into a 100 s wait
    assert clock.wait(ev, 100.0) is True
    assert 2.0 < clock.now() < 60.0
