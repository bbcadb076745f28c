"""A move the motion gate refuses during a campaign names the plan's pose it was a move
to, as the engine names poses (``pose 1: robot: refused …``), in the error and in the
campaign's ``device-error`` event; the service still knows which device it was."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.calib.kinematics import flange_transforms
from cellcal.campaign.engine import SensorSetting, acquire
from cellcal.campaign.plan import CALIBRATION, Plan, PlannedPose
from cellcal.campaign.records import CampaignEvent, RecordStream
from cellcal.clock import SimulatedClock
from cellcal.config import config_from_dict
from cellcal.drivers.base import Series
from cellcal.drivers.safety import GuardedRobot, SafetyError
from cellcal.errors import DeviceError
from cellcal.files.models import load_model
from cellcal.service.worker import faulty_device

KR5 = load_model("kuka-kr5-arc").model
TOOL = np.array([25.0, -40.0, 130.0])
Q0 = np.radians([-45.0, -30.0, 40.0, 0.0, -20.0, 0.0])
Q1 = np.radians([45.0, -30.0, 40.0, 0.0, -20.0, 0.0])


class Robot:
    """A robot at ``q`` that goes where it is sent (``off``: that far beside it)."""

    name = "robot"

    def __init__(self, q: np.ndarray, off: float = 0.0) -> None:
        self.q = np.array(q, dtype=float)
        self.off = off
        self.moves: list[np.ndarray] = []

    def connect(self) -> None:
        """Nothing to connect: the robot is this object."""

    def move_joints(self, q: np.ndarray, speed: float) -> None:
        self.moves.append(np.array(q))
        self.q = np.array(q) + self.off

    def actual_joints(self) -> np.ndarray:
        return self.q

    def stop(self) -> None:
        """It never moves by itself: nothing to stop."""

    def close(self) -> None:
        """Nothing to close."""


class Sensor:
    name = "tracker"

    def connect(self) -> None:
        """Nothing to connect."""

    def measure(self, n: int, rate_hz: float) -> Series:
        t = np.arange(n, dtype=float)
        return Series(self.name, t, t, np.zeros((n, 3)))

    def close(self) -> None:
        """Nothing to close."""


def _box() -> tuple[np.ndarray, np.ndarray]:
    """Around the flange and the target at both ends, 20 mm to spare: the joint move
    from Q0 to Q1 swings out of it on the way."""
    T = flange_transforms(KR5, np.array([Q0, Q1]))
    pts = np.concatenate([T[:, :3, 3], T[:, :3, 3] + T[:, :3, :3] @ TOOL])
    return pts.min(axis=0) - 20.0, pts.max(axis=0) + 20.0


def _acquire(robot: object) -> tuple[BaseException, list[CampaignEvent]]:
    plan = Plan(
        tuple(PlannedPose(i, CALIBRATION, "cube", np.zeros(3), q) for i, q in enumerate((Q0, Q1))),
        (),
    )
    events: list[CampaignEvent] = []
    stream = RecordStream()
    stream.subscribe(lambda r: events.append(r) if isinstance(r, CampaignEvent) else None)
    with pytest.raises(DeviceError) as info:
        acquire(
            plan,
            robot,  # type: ignore[arg-type]
            [SensorSetting(Sensor(), 10.0)],
            SimulatedClock(),
            campaign_id=1,
            done=set(),
            stream=stream,
            dwell_s=0.0,
            samples_per_pose=2,
            speed=0.25,
        )
    return info.value, events


@pytest.mark.timeout(60)
def test_a_refused_move_names_its_pose_as_the_engine_does() -> None:
    lo, hi = _box()
    inner = Robot(Q0)
    error, events = _acquire(GuardedRobot(inner, KR5, TOOL, lo, hi, 0.5))
    line = str(error)
    assert isinstance(error, SafetyError)
    assert line.startswith("pose 1: robot: refused the move from "), line
    assert "on the way" in line and "\n" not in line
    assert len(inner.moves) == 1  # pose 0 (where it stands) was visited; pose 1 never sent
    (event,) = [e for e in events if e.kind == "device-error"]
    assert event.message == line and event.pose_idx == 1
    # the service still finds the device the line is about
    config = config_from_dict(
        {"sensor": [{"name": "tracker", "kind": "laser-tracker", "reference": True}]}
    )
    assert faulty_device(config, line) == "robot"


@pytest.mark.timeout(60)
def test_a_robot_not_in_position_is_named_the_same_way() -> None:
    error, _ = _acquire(Robot(Q0, off=0.01))
    assert str(error).startswith("pose 0: robot: reports "), str(error)
