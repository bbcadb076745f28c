"""The handshake's next move waits for a command the controller still holds
(cellcal/drivers/stop_and_measure.py): a controller program that answers ``ack = seq``
with the number requested *then* would otherwise acknowledge the next move's number at
the end of the stopped one, and the move would be taken for done without moving — found
by the independent KUKAVARPROXY fake (tests/fakes/kvp_fake.py) once in a full run."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.calib.geometry import Array
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot
from cellcal.errors import DeviceError


class Scripted(HandshakeRobot):
    """A controller whose loop moves in no time and answers at once, except while it
    hangs (``hang``); a hanging loop acts on a stop ``release`` readings after it (None:
    never) by abandoning the move and answering ``ack = seq`` with the number requested
    *then*."""

    family = "scripted"

    def __init__(self) -> None:
        super().__init__("robot", "here", timeout_s=0.3, poll_s=0.001)
        self.seq = self.ack = 4
        self.hang, self.release, self.stops = False, None, 0
        self.readings = 0
        self.q_deg = np.zeros(6)
        self.sent: list[tuple[int, int]] = []  # (sequence number, readings before)

    def _open(self) -> None:
        return None

    def _close(self) -> None:
        return None

    def _state(self) -> ControllerState:
        self.readings += 1
        if self.stops and self.release is not None and self.readings >= self.release:
            self.ack, self.stops, self.hang = self.seq, 0, False
        return ControllerState(None, None, False, self.ack, f"seq {self.seq}", self.seq, "CC_SEQ")

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        self.sent.append((seq, self.readings))
        self.seq = seq
        if not self.hang:
            self.q_deg, self.ack = np.asarray(target_deg), seq

    def _read_joints_deg(self) -> Array:
        return self.q_deg

    def _send_stop(self) -> None:
        self.stops += 1


TARGET = np.radians([10.0, -20.0, 30.0, 0.0, 15.0, 0.0])


def _stopped_move(robot: Scripted) -> None:
    robot.hang = True
    with pytest.raises(DeviceError, match=r"move not done after 0.3 s \(sequence 5"):
        robot.move_joints(np.radians([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), 0.5)
    assert robot.stops == 1 and (robot.seq, robot.ack) == (5, 4)


def test_the_move_after_a_stopped_one_waits_for_its_acknowledgement() -> None:
    robot = Scripted()
    _stopped_move(robot)
    robot.release = robot.readings + 3  # the loop acts on the stop three readings on
    robot.move_joints(TARGET, 0.5)
    # the new number went out once the stopped one was acknowledged: a number sent
    # earlier would have been acknowledged by the stopped move's end
    assert robot.sent[-1] == (6, robot.release)
    np.testing.assert_allclose(np.radians(robot.q_deg), TARGET)


def test_a_stopped_move_never_acknowledged_refuses_the_next_in_one_line() -> None:
    robot = Scripted()
    _stopped_move(robot)
    robot.hang = False
    with pytest.raises(DeviceError) as err:
        robot.move_joints(TARGET, 0.5)
    assert [seq for seq, _ in robot.sent] == [5]
    assert str(err.value) == (
        "robot at here: move refused: the controller has not acknowledged the stopped move "
        "(CC_SEQ 5) after 0.3 s (seq 5); is its program running?"
    )
    # it is not waited for again: the operator has seen the line
    robot.move_joints(TARGET, 0.5)
    assert robot.sent[-1][0] == 6


def test_a_move_the_controller_refused_is_replaced_at_once() -> None:
    """A stop message leaves the request unanswered without any stop from the driver:
    the next move replaces it, as before."""
    robot = Scripted()
    robot.seq = 5  # requested, never answered
    robot.move_joints(TARGET, 0.5)
    assert robot.sent == [(5, 1)]  # the acknowledgement's next number, with the new target
    np.testing.assert_allclose(np.radians(robot.q_deg), TARGET)


def test_an_idle_controller_is_moved_at_once() -> None:
    robot = Scripted()
    robot.move_joints(TARGET, 0.5)
    assert robot.sent == [(5, 1)]
