"""Stand-ins for a campaign's devices, and the engine run on them, for the tests of what
the engine and the motion gate say when a move or a device fails
(``test_device_descriptions.py``, ``test_gate_names_the_pose.py``,
``tests/test_motion_gate.py``): a robot that goes where it is sent (or beside it, or
nowhere), a sensor that measures zeros (or fails); and the KR 5 arc with a target on its
flange and a joint move, Q0 to Q1, whose flange swings out in x on the way."""

from __future__ import annotations

import numpy as np

from cellcal.calib.kinematics import flange_transforms
from cellcal.campaign.engine import SensorSetting, acquire
from cellcal.campaign.plan import CALIBRATION, Plan, PlannedPose
from cellcal.campaign.records import CampaignEvent, RecordStream
from cellcal.clock import SimulatedClock
from cellcal.drivers.base import Series
from cellcal.errors import DeviceError
from cellcal.files.models import load_model

KR5 = load_model("kuka-kr5-arc").model
TOOL = np.array([25.0, -40.0, 130.0])
Q0 = np.radians([-45.0, -30.0, 40.0, 0.0, -20.0, 0.0])
Q1 = np.radians([45.0, -30.0, 40.0, 0.0, -20.0, 0.0])


class Robot:
    """A robot at ``q`` that records the moves sent to it and goes where it is sent
    (``off``: that far beside it), or raises ``fault`` (a DeviceError that names
    nothing) instead."""

    def __init__(
        self,
        q: np.ndarray,
        off: float = 0.0,
        fault: DeviceError | None = None,
        name: str = "robot",
    ) -> None:
        self.q = np.array(q, dtype=float)
        self.off, self.fault, self.name = off, fault, name
        self.moves: list[np.ndarray] = []

    def connect(self) -> None:
        """Nothing to connect: the robot is this object."""

    def move_joints(self, q: np.ndarray, speed: float) -> None:
        if self.fault is not None:
            raise self.fault
        self.moves.append(np.array(q))
        self.q = np.array(q) + self.off

    def actual_joints(self) -> np.ndarray:
        return self.q

    def stop(self) -> None:
        """It never moves by itself: nothing to stop."""

    def close(self) -> None:
        """Nothing to close."""


class Sensor:
    """Measures zeros, or raises ``fault`` every time (a DeviceError that names nothing)."""

    def __init__(self, name: str = "tracker", fault: DeviceError | None = None) -> None:
        self.name, self.fault = name, fault

    def connect(self) -> None:
        """Nothing to connect."""

    def measure(self, n: int, rate_hz: float) -> Series:
        if self.fault is not None:
            raise self.fault
        t = np.arange(n, dtype=float)
        return Series(self.name, t, t, np.zeros((n, 3)))

    def close(self) -> None:
        """Nothing to close."""


def acquire_at(
    robot: object, sensors: list[Sensor], *qs: np.ndarray
) -> tuple[DeviceError | None, list[CampaignEvent]]:
    """The engine through calibration poses at the joints ``qs`` on these devices (no
    dwell, two samples at 10 Hz): the DeviceError it ended in (None: none) and the
    campaign's events."""
    poses = (PlannedPose(i, CALIBRATION, "cube", np.zeros(3), q) for i, q in enumerate(qs))
    events: list[CampaignEvent] = []
    stream = RecordStream()
    stream.subscribe(lambda r: events.append(r) if isinstance(r, CampaignEvent) else None)
    try:
        acquire(
            Plan(tuple(poses), ()),
            robot,  # type: ignore[arg-type]
            [SensorSetting(s, 10.0) for s in sensors],  # type: ignore[arg-type]
            SimulatedClock(),
            campaign_id=1,
            done=set(),
            stream=stream,
            dwell_s=0.0,
            samples_per_pose=2,
            speed=0.25,
        )
    except DeviceError as exc:
        return exc, events
    return None, events


def flange_and_target(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the KR 5 arc's flange and the target on it (TOOL) are at the joints ``q``
    (one or more rows; mm)."""
    T = flange_transforms(KR5, np.atleast_2d(q))
    return T[:, :3, 3], T[:, :3, 3] + T[:, :3, :3] @ TOOL


def box_around_the_ends() -> tuple[np.ndarray, np.ndarray]:
    """A box that holds the flange and the target at Q0 and at Q1, with 20 mm to spare:
    the joint move from Q0 to Q1 swings out of it on the way."""
    pts = np.concatenate([*flange_and_target(Q0), *flange_and_target(Q1)])
    return pts.min(axis=0) - 20.0, pts.max(axis=0) + 20.0
