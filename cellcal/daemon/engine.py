"""The engine: executes a plan, pose by pose, and stores every sample.

Per pose: move → (the driver returns once the robot reports it is in position) →
dwell on the clock → sample every sensor concurrently → store the pose, its raw samples
and their statistics in one transaction. Poses already stored (a resumed campaign) are
skipped. A stop request (Ctrl-C, SIGTERM) is honoured between steps: the pose under way
is abandoned unstored, so the campaign stays resumable and loses nothing.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from cellcal.clock import Clock
from cellcal.daemon.plan import Plan, PlannedPose
from cellcal.daemon.store import Store
from cellcal.drivers.base import PositionSensor, Robot, Series
from cellcal.errors import DeviceError

#: A reached joint position further than this from the plan (rad) is refused.
IN_POSITION_TOL = 1e-3
#: A sensor that fails at a pose (after its own driver's retries) is asked again this often.
SAMPLE_RETRIES = 2


class Progress(Protocol):
    def start(self, total: int, done: int) -> None: ...

    def advance(self, pose: PlannedPose, done: int, total: int) -> None: ...

    def finish(self) -> None: ...


class NoProgress:
    def start(self, total: int, done: int) -> None:
        pass

    def advance(self, pose: PlannedPose, done: int, total: int) -> None:
        pass

    def finish(self) -> None:
        pass


@dataclass(frozen=True)
class SensorSetting:
    sensor: PositionSensor
    rate_hz: float


@dataclass(frozen=True)
class Acquisition:
    """How an acquisition ended: poses stored in all, stored now, interrupted or not,
    and the clock seconds it took."""

    stored: int
    stored_now: int
    interrupted: bool
    clock_seconds: float


def acquire(
    store: Store,
    campaign_id: int,
    plan: Plan,
    robot: Robot,
    sensors: Sequence[SensorSetting],
    clock: Clock,
    *,
    dwell_s: float,
    samples_per_pose: int,
    speed: float,
    stop: threading.Event | None = None,
    progress: Progress | None = None,
) -> Acquisition:
    """Visit every planned pose not yet stored; see the module docstring."""
    stop = stop or threading.Event()
    progress = progress or NoProgress()
    done = store.completed_indices(campaign_id)
    todo = [p for p in plan.poses if p.idx not in done]
    total = len(plan.poses)
    progress.start(total, len(done))
    t0 = clock.now()
    stored_now = 0
    interrupted = False
    with ThreadPoolExecutor(max_workers=max(1, len(sensors)), thread_name_prefix="sensor") as pool:
        for pose in todo:
            if stop.is_set():
                interrupted = True
                break
            try:
                stored = _visit(
                    store,
                    campaign_id,
                    pose,
                    robot,
                    sensors,
                    clock,
                    pool,
                    stop,
                    dwell_s=dwell_s,
                    samples_per_pose=samples_per_pose,
                    speed=speed,
                )
            except DeviceError as exc:
                store.add_event(campaign_id, "device-error", str(exc), pose.idx)
                raise
            if not stored:
                interrupted = True
                break
            stored_now += 1
            progress.advance(pose, len(done) + stored_now, total)
    if interrupted:
        robot.stop()
    progress.finish()
    return Acquisition(len(done) + stored_now, stored_now, interrupted, clock.now() - t0)


def _visit(
    store: Store,
    campaign_id: int,
    pose: PlannedPose,
    robot: Robot,
    sensors: Sequence[SensorSetting],
    clock: Clock,
    pool: ThreadPoolExecutor,
    stop: threading.Event,
    *,
    dwell_s: float,
    samples_per_pose: int,
    speed: float,
) -> int:
    """One pose: 1 if stored, 0 if a stop request came first."""
    t_start = clock.now()
    robot.move_joints(pose.q, speed)
    reached = robot.actual_joints()
    if float(np.max(np.abs(reached - pose.q))) > IN_POSITION_TOL:
        raise DeviceError(
            f"{robot.name}: reports {np.degrees(reached).round(3).tolist()}° after a "
            f"move to {np.degrees(pose.q).round(3).tolist()}° (pose {pose.idx})"
        )
    if stop.is_set():
        return 0
    clock.sleep(dwell_s)
    if stop.is_set():
        return 0
    start = clock.now()

    def sample(s: SensorSetting) -> Series:
        with clock.branch(start):
            return s.sensor.measure(samples_per_pose, s.rate_hz)

    for attempt in range(SAMPLE_RETRIES + 1):
        try:
            series = [f.result() for f in [pool.submit(sample, s) for s in sensors]]
            break
        except DeviceError as exc:
            if attempt == SAMPLE_RETRIES:
                raise
            # The pose is still where it should be: measure it again, once or twice.
            store.add_event(campaign_id, "sensor-retry", str(exc), pose.idx)
            start = clock.now()
    store.add_pose(
        campaign_id,
        idx=pose.idx,
        role=pose.role,
        region=pose.region,
        target_mm=pose.target_mm,
        planned_q=pose.q,
        reached_q=reached,
        t_start=t_start,
        t_end=clock.now(),
        series=series,
    )
    return 1
