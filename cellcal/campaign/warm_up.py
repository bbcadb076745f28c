"""The warm-up gate: ``[campaign] warm_up_s`` runs the robot through the plan's
calibration poses, in order and over again, without measuring, before the first pose is
measured (at a campaign's start and when it resumes), so that a drift with the arm's
temperature is behind it rather than in the data.

The gate lasts ``warm_up_s`` of the campaign's clock (with a pause of :data:`PAUSE_S` at
each pose); where the robot's driver reads the
joints' temperatures (a UR through RTDE) it ends earlier once every joint changed less
than ``warm_up_settled_c_per_min`` over the last minute. A stop request ends it at once
(nothing is stored by a warm-up). Its ``warm-up`` event says how long it ran, how many
moves, and the temperatures where they were read.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from cellcal.campaign.plan import CALIBRATION, Plan
from cellcal.campaign.records import CampaignEvent, RecordStream
from cellcal.clock import Clock
from cellcal.drivers.base import ROBOT_NAME, Robot
from cellcal.errors import device_errors

WARM_UP = "warm-up"
#: the window (s) over which the temperatures must have settled
SETTLE_WINDOW_S = 60.0
#: the pause at each pose of the warm-up (s of the campaign's clock): the clock moves on
#: even where a move takes none of it (a simulated clock and a twin's moves)
PAUSE_S = 1.0


def _temperatures(robot: Robot) -> np.ndarray | None:
    read = getattr(robot, "joint_temperatures", None)
    if read is None:
        return None
    got = read()
    return None if got is None else np.asarray(got, dtype=np.float64)


def _settled(history: Sequence[tuple[float, np.ndarray]], rate_c_per_min: float) -> bool:
    """Whether every joint changed less than ``rate_c_per_min`` over the last window."""
    if rate_c_per_min <= 0 or len(history) < 2:
        return False
    t_end, last = history[-1]
    earlier = [(t, temps) for t, temps in history if t <= t_end - SETTLE_WINDOW_S]
    if not earlier:
        return False
    t0, first = earlier[-1]
    per_min = np.abs(last - first) / ((t_end - t0) / 60.0)
    return bool((per_min < rate_c_per_min).all())


def warm_up(
    plan: Plan,
    robot: Robot,
    clock: Clock,
    stream: RecordStream,
    *,
    campaign_id: int,
    seconds: float,
    settled_c_per_min: float,
    speed: float,
    halted: Callable[[], bool],
) -> bool:
    """Run the warm-up; False when ``halted()`` (a stop or pause request) ended it."""
    poses = [p.q for p in plan.poses if p.role == CALIBRATION] or [p.q for p in plan.poses]
    if seconds <= 0 or not poses:
        return True
    start = clock.now()
    moves = 0
    history: list[tuple[float, np.ndarray]] = []
    why = "its time ran out"
    with device_errors(ROBOT_NAME):
        while clock.now() - start < seconds:
            if halted():
                return False
            robot.move_joints(poses[moves % len(poses)], speed)
            moves += 1
            clock.sleep(PAUSE_S)
            temps = _temperatures(robot)
            if temps is not None:
                history.append((clock.now(), temps))
                if _settled(history, settled_c_per_min):
                    why = f"the joints' temperatures settled (< {settled_c_per_min:g} °C/min)"
                    break
    said = f"warm-up: {clock.now() - start:.0f} s, {moves} moves through the plan's poses; {why}"
    if history:
        last = history[-1][1]
        said += f"; joint temperatures {last.min():.1f}–{last.max():.1f} °C"
    stream.emit(CampaignEvent(campaign_id, WARM_UP, said, None, clock.now()))
    return True
