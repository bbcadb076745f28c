"""The motion gate checks the path, not only the end (issue 29, item 2): the robots'
moves are joint moves (straight in joint space), and a move whose flange or target
leaves the workspace box on the way, or whose joints leave the limits, is refused with
one line naming the pose and by how much, before anything is sent."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.campaign.devices import build_devices
from cellcal.clock import SimulatedClock
from cellcal.config import config_from_dict
from cellcal.drivers.safety import GuardedRobot, SafetyError
from tests.conftest import TRACKER_CELL, tracker_cell
from tests.daemon.stand_ins import KR5, Q0, Q1, TOOL, Robot, box_around_the_ends, flange_and_target
from tests.inprocess import cellcal


def _worst_outside(lo, hi):
    """How far the path's flange and target go outside the box, by brute force."""
    s = np.linspace(0, 1, 20001)[:, None]
    flange, target = flange_and_target(Q0 + s * (Q1 - Q0))
    p = np.concatenate([flange, target])
    d = np.maximum(lo - p, 0) + np.maximum(p - hi, 0)
    return float(np.linalg.norm(d, axis=1).max())


def test_a_move_whose_path_leaves_the_box_is_refused_and_says_by_how_much():
    lo, hi = box_around_the_ends()
    robot = Robot(Q0)
    gate = GuardedRobot(robot, KR5, TOOL, lo, hi, 0.5)
    gate.check(Q1, 0.25)  # the end alone is inside the box
    worst = _worst_outside(lo, hi)
    assert worst > 100.0  # the arm swings out in x on the way
    with pytest.raises(SafetyError) as info:
        gate.move_joints(Q1, 0.25)
    line = str(info.value)
    assert "\n" not in line and "on the way" in line and "workspace box" in line, line
    assert "[45.0, -30.0, 40.0, 0.0, -20.0, 0.0]" in line  # the pose asked for
    said = float(line.split("leaves the workspace box by ")[1].split(" mm")[0])
    assert said == pytest.approx(worst, abs=1.0)
    assert robot.moves == [] and gate.refused == 1
    # The same move inside a box that holds its whole path is sent.
    wide = GuardedRobot(robot, KR5, TOOL, lo - 300.0, hi + 300.0, 0.5)
    wide.move_joints(Q1, 0.25)
    assert len(robot.moves) == 1


def test_a_robot_outside_its_limits_or_the_box_is_not_moved():
    lo, hi = box_around_the_ends()
    beyond = Q0.copy()
    beyond[2] = np.radians(170.0)  # A3 beyond +158°
    robot = Robot(beyond)
    with pytest.raises(SafetyError, match=r"the robot is at: joint 3 to 170\.000°"):
        GuardedRobot(robot, KR5, TOOL, lo - 1e3, hi + 1e3, 0.5).move_joints(Q0, 0.25)
    out = Robot(Q0)
    gate = GuardedRobot(
        out, KR5, TOOL, lo + np.array([300.0, 0, 0]), hi + np.array([300.0, 0, 0]), 0.5
    )
    with pytest.raises(SafetyError):
        gate.move_joints(Q1, 0.25)
    assert robot.moves == [] and out.moves == []


@pytest.mark.twin
@pytest.mark.timeout(120)
def test_the_campaigns_robot_refuses_such_a_move_before_the_controller_sees_it():
    """Through the device factory: the real Modbus driver behind the gate, its twin."""
    lo, hi = box_around_the_ends()
    config = tracker_cell()
    data = config.model_dump()
    data["robot"]["home_deg"] = np.degrees(Q0).tolist()
    data["campaign"]["workspace_min_mm"] = lo.tolist()
    data["campaign"]["workspace_max_mm"] = hi.tolist()
    config = config_from_dict(data, "test")
    devices = build_devices(config, KR5, SimulatedClock(), mock=True, seed=1)
    try:
        with pytest.raises(SafetyError, match="on the way"):
            devices.robot.move_joints(Q1, 0.25)
        np.testing.assert_allclose(devices.simulated_cell.q, Q0, atol=1e-9)
    finally:
        devices.close()


@pytest.mark.timeout(120)
def test_the_plan_says_which_moves_would_leave_the_box(tmp_path):
    """A box around the cube and the regions, 20 mm to spare: some of the bundled plan's
    128 moves swing out of it on the way; ``cellcal plan`` names them and by how much,
    as the gate would refuse them."""
    lo, hi = [330.0, -945.0, 298.0], [1149.0, 1032.0, 1139.0]
    text = TRACKER_CELL.read_text().replace(
        "[campaign]\n", f"[campaign]\nworkspace_min_mm = {lo}\nworkspace_max_mm = {hi}\n"
    )
    cell = tmp_path / "cell.toml"
    cell.write_text(text)
    run = cellcal("plan", "--config", cell, "--json")
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    leaving = s.get("moves_leaving_box")
    assert leaving is not None and len(leaving) >= 10, leaving
    from cellcal.drivers.safety import path_excursion  # (the function the gate samples with)

    q = {p["idx"]: np.radians(p["q_deg"]) for p in s["poses"] if p["idx"] is not None}
    home = np.radians(tracker_cell().robot.home_deg)
    for m in leaving:
        k = m["idx"]
        e = path_excursion(KR5, q[k - 1] if k else home, q[k], TOOL, np.array(lo), np.array(hi))
        assert e is not None and abs(e.excess_mm - m["excess_mm"]) < 1e-3
    run = cellcal("plan", "--config", cell)
    assert "moves leave the workspace box on the way, which the safety gate refuses" in run.stdout
