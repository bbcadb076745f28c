"""The warm-up gate against a known truth: a robot whose joints warm on the campaign's
clock; the gate runs the plan's poses until they settle (or its time runs out), says so
in its event, and a stop request ends it."""

from __future__ import annotations

import math

import numpy as np

from cellcal.campaign.plan import CALIBRATION, Plan, PlannedPose
from cellcal.campaign.records import CampaignEvent, RecordStream
from cellcal.campaign.warm_up import WARM_UP, warm_up
from cellcal.clock import SimulatedClock

TAU_S = 600.0


class WarmingRobot:
    """Moves at once; its joints warm by 8 °C towards 35 °C with time constant TAU_S
    (None: it reads no temperatures)."""

    name = "robot"

    def __init__(self, clock: SimulatedClock, reads: bool = True) -> None:
        self.clock, self.moves = clock, []
        if not reads:
            self.joint_temperatures = None  # type: ignore[assignment]

    def move_joints(self, q, speed):  # type: ignore[no-untyped-def]
        self.moves.append(np.array(q))

    def joint_temperatures(self):  # type: ignore[no-untyped-def]
        return np.full(6, 35.0 - 8.0 * math.exp(-self.clock.now() / TAU_S))


def _plan() -> Plan:
    poses = tuple(
        PlannedPose(i, CALIBRATION, "cube", np.zeros(3), np.full(6, 0.1 * i)) for i in range(5)
    )
    return Plan(poses, ())


def _run(robot: WarmingRobot, clock: SimulatedClock, seconds: float, halted=lambda: False):  # type: ignore[no-untyped-def]
    events: list[CampaignEvent] = []
    stream = RecordStream()
    stream.subscribe(lambda r: events.append(r) if isinstance(r, CampaignEvent) else None)
    ok = warm_up(
        _plan(),
        robot,
        clock,
        stream,
        campaign_id=1,
        seconds=seconds,
        settled_c_per_min=0.1,
        speed=0.25,
        halted=halted,
    )
    return ok, events


def test_the_gate_ends_when_the_joints_have_settled() -> None:
    clock = SimulatedClock()
    robot = WarmingRobot(clock)
    ok, events = _run(robot, clock, 3600.0)
    (event,) = events
    assert ok and event.kind == WARM_UP and "settled (< 0.1 °C/min)" in event.message
    # 8/τ·exp(−t/τ) °C/s = 0.8·exp(−t/τ) °C/min < 0.1 once t > τ·ln 8 ≈ 1248 s; the
    # rate over the last minute gets there half a minute later
    assert 1248.0 < clock.now() < 1248.0 + 60.0
    assert len(robot.moves) == round(clock.now())  # a second at each pose
    assert np.array_equal(robot.moves[6], _plan().poses[1].q)  # through the poses, again


def test_without_temperatures_the_gate_runs_its_time() -> None:
    clock = SimulatedClock()
    ok, events = _run(WarmingRobot(clock, reads=False), clock, 120.0)
    assert (
        ok and "120 s, 120 moves" in events[0].message and "its time ran out" in events[0].message
    )


def test_a_stop_request_ends_the_warm_up() -> None:
    clock = SimulatedClock()
    robot = WarmingRobot(clock)
    ok, events = _run(robot, clock, 3600.0, halted=lambda: len(robot.moves) >= 10)
    assert not ok and events == [] and len(robot.moves) == 10
