"""A move the motion gate refuses during a campaign names the plan's pose it was a move
to, as the engine names poses (``pose 1: robot: refused …``), in the error and in the
campaign's ``device-error`` event; the service still knows which device it was."""

from __future__ import annotations

import pytest

from cellcal.config import config_from_dict
from cellcal.drivers.safety import GuardedRobot, SafetyError
from cellcal.service.worker import faulty_device
from tests.daemon.stand_ins import KR5, Q0, Q1, TOOL, Robot, Sensor, acquire_at, box_around_the_ends


@pytest.mark.timeout(60)
def test_a_refused_move_names_its_pose_as_the_engine_does() -> None:
    lo, hi = box_around_the_ends()
    inner = Robot(Q0)
    error, events = acquire_at(GuardedRobot(inner, KR5, TOOL, lo, hi, 0.5), [Sensor()], Q0, Q1)
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
    error, _ = acquire_at(Robot(Q0, off=0.01), [Sensor()], Q0, Q1)
    assert error is not None
    assert str(error).startswith("pose 0: robot: reports "), str(error)
