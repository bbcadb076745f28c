"""The safety gate in front of every robot driver."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.drivers.safety import GuardedRobot, SafetyError
from cellcal.files.models import load_model


class Recorder:
    name = "recorder"

    def __init__(self):
        self.moves = []
        self.stopped = 0

    def connect(self):
        pass

    def move_joints(self, q, speed):
        self.moves.append((np.array(q), speed))

    def actual_joints(self):
        # a robot is somewhere before its first move: home (the gate checks the path)
        return self.moves[-1][0] if self.moves else np.radians([0, -30, 40, 0, -20, 0])

    def stop(self):
        self.stopped += 1

    def close(self):
        pass


def _guard(**kw):
    model = load_model("kuka-kr5-arc").model
    robot = Recorder()
    args = {"box_min_mm": [-1500, -1500, 0], "box_max_mm": [1500, 1500, 2000], "max_speed": 0.5}
    args.update(kw)
    return GuardedRobot(robot, model, np.array([25.0, -40.0, 130.0]), **args), robot


def test_a_safe_move_is_sent():
    g, robot = _guard()
    q = np.radians([0, -30, 40, 0, -20, 0])
    g.move_joints(q, 0.25)
    assert len(robot.moves) == 1 and g.refused == 0
    g.stop()
    assert robot.stopped == 1


@pytest.mark.parametrize(
    ("q_deg", "speed", "kw", "match"),
    [
        (
            [0, -30, 170, 0, -20, 0],
            0.25,
            {},
            r"joint 3 to 170\.000° is outside \[-15\.0°, 158\.0°\]",
        ),
        ([0, -30, 40, 0, -20, 0], 0.9, {}, "speed 0.9; the limit is 0.5"),
        ([0, -30, 40, 0, -20, 0], 0.0, {}, "speed 0"),
        (
            [0, -30, 40, 0, -20, 0],
            0.25,
            {"box_max_mm": [1500, 1500, 500]},
            "outside the workspace box",
        ),
        ([0, -30, 40, 0, -20], 0.25, {}, "malformed"),
        ([0, -30, float("nan"), 0, -20, 0], 0.25, {}, "malformed"),
    ],
)
def test_unsafe_moves_are_never_sent(q_deg, speed, kw, match):
    g, robot = _guard(**kw)
    with pytest.raises(SafetyError, match=match):
        g.move_joints(np.radians(q_deg), speed)
    assert robot.moves == [] and g.refused == 1
