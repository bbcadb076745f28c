"""cellcal's FANUC RMI driver against a fake controller written by another hand from
docs/robots.md and the manual's packet list alone (tests/fakes/rmi_fake.py, not from cellcal's
twin), over real sockets on 127.0.0.17–.18: moves, the measured joints, the sequence ids, and
the faults a cell meets. The fake writes its integer fields as integral floats (``0.0``), its
joint angles with noise and all their digits, its keys after the first in reverse order with
an unknown one among them, and sends its answers in pieces of a few dozen bytes; its session
port is ephemeral, RMI outlives a session there, and a session ended is freed a moment later."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from cellcal.drivers.fanuc_rmi import FanucRmiOptions, FanucRmiRobot
from cellcal.errors import DeviceError
from tests.fakes.rmi_fake import RmiFake

pytestmark = pytest.mark.timeout(60)

ALARM = "SRVO-050 Collision Detect alarm (G:1 A:3)"


def _robot(
    host: str,
    port: int,
    request_timeout_s: float = 2.0,
    uframe: int | None = None,
    utool: int | None = None,
) -> FanucRmiRobot:
    options = FanucRmiOptions(
        address=f"{host}:{port}",
        move_timeout_s=10.0,
        request_timeout_s=request_timeout_s,
        uframe=uframe,
        utool=utool,
    )
    return FanucRmiRobot(host, port, options=options)


def _until(what: Callable[[], bool], why: str, within_s: float = 5.0) -> None:
    deadline = time.monotonic() + within_s
    while not what():
        assert time.monotonic() < deadline, why
        time.sleep(0.005)


def _one_line(e: pytest.ExceptionInfo[DeviceError], host: str, port: int) -> str:
    text = str(e.value)
    assert "\n" not in text
    assert f"fanuc-robot at {host}:{port}" in text
    return text


def test_the_driver_moves_and_reads_through_another_fake() -> None:
    fake = RmiFake(time_scale=0.01)
    host, port = fake.start("127.0.0.17", 0)
    try:
        with _robot(host, port) as r:
            np.testing.assert_allclose(
                np.degrees(r.actual_joints()), [0, -20, 15, 0, -45, 0], atol=1e-3
            )
            targets = ([10.5, -30.25, 20.0, 5.0, -40.0, 90.0], [-20, 0, 0, 0, 0, 0], [0] * 6)
            for target in targets:
                r.move_joints(np.radians(target), 0.5)
                np.testing.assert_allclose(np.degrees(r.actual_joints()), target, atol=1e-3)
                np.testing.assert_allclose(fake.q_deg(), target, atol=1e-9)
            assert "3.7" in str(r.describe().firmware)
        assert fake.sequence_ids() == [1, 2, 3]
        moves = fake.packets("FRC_JointMotionJRep")
        assert [m["SpeedType"] for m in moves] == ["Percent"] * 3
        assert all(m["TermType"] in ("FINE", "CNT") for m in moves)
        assert fake.packets("FRC_Initialize") == [{"Command": "FRC_Initialize", "GroupMask": 1}]
        assert fake.packets("FRC_Disconnect")
        # the fake did split its answers: some piece it wrote ends inside a packet
        assert any(not s.endswith(b"\r\n") for s in fake.segments)
    finally:
        fake.stop()


def test_the_user_frame_and_tool_are_set_when_configured() -> None:
    fake = RmiFake(time_scale=0.01, uframe=0, utool=1)
    host, port = fake.start("127.0.0.17", 0)
    try:
        with _robot(host, port, uframe=2, utool=3) as r:
            r.move_joints(np.radians([2, -20, 15, 0, -45, 0]), 0.5)
        sets = fake.packets("FRC_SetUFrameUTool")
        assert [(p["UFrameNumber"], p["UToolNumber"]) for p in sets] == [(2, 3)]
        assert fake.sequence_ids() == [1]
    finally:
        fake.stop()


def test_a_second_client_is_refused_in_one_line() -> None:
    fake = RmiFake(time_scale=0.01)
    host, port = fake.start("127.0.0.17", 0)
    try:
        with _robot(host, port) as r:
            with pytest.raises(DeviceError) as e:
                _robot(host, port, request_timeout_s=0.5).connect()
            text = _one_line(e, host, port)
            assert "connect refused: ErrorID 2556954" in text
            assert fake.connect_refusals >= 1 and fake.sessions == 1
            r.move_joints(np.radians([5, -20, 15, 0, -45, 0]), 0.3)  # the first one still moves
        assert fake.sequence_ids() == [1]
    finally:
        fake.stop()


def test_the_teach_pendant_and_the_servo_are_refused_in_one_line() -> None:
    fake = RmiFake(time_scale=0.01)
    host, port = fake.start("127.0.0.18", 0)
    try:
        fake.tp_enabled = True
        with pytest.raises(DeviceError) as e:
            _robot(host, port).connect()
        assert "connect refused: the teach pendant is enabled" in _one_line(e, host, port)
        fake.tp_enabled = False
        fake.servo_off = True
        with pytest.raises(DeviceError) as e:
            _robot(host, port).connect()
        assert "connect refused: the servo is not ready" in _one_line(e, host, port)
        fake.servo_off = False
        with _robot(host, port) as r:
            r.move_joints(np.radians([1, -20, 15, 0, -45, 0]), 0.3)
        assert fake.sequence_ids() == [1]
    finally:
        fake.stop()


@pytest.mark.parametrize("fault_answer", [None, 2556952])
def test_an_alarm_mid_move_ends_it_in_one_line_and_a_new_session_resumes(
    fault_answer: int | None,
) -> None:
    fake = RmiFake(time_scale=0.05, fault_answer=fault_answer)
    host, port = fake.start("127.0.0.18", 0)
    try:
        with _robot(host, port) as r:
            r.move_joints(np.radians([10, -20, 15, 0, -45, 0]), 0.5)
            fake.raise_alarm(ALARM)
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([40, -20, 15, 0, -45, 0]), 0.5)
            text = _one_line(e, host, port)
            assert "system fault during the move (sequence 2)" in text
            assert ALARM in text
            assert fake.alarm == ALARM
            assert 10.0 < fake.q_deg()[0] < 40.0  # stopped on its way
            if fault_answer is not None:  # the fault and the instruction's answer, glued
                assert any(b"}\r\n{" in s and b"FRC_JointMotionJRep" in s for s in fake.segments)
        with _robot(host, port) as r:  # resume: reset, abort, initialise again
            assert fake.alarm is None
            r.move_joints(np.radians([40, -20, 15, 0, -45, 0]), 0.5)
            np.testing.assert_allclose(np.degrees(r.actual_joints())[0], 40.0, atol=1e-3)
        assert fake.sequence_ids() == [1, 2, 1]
        assert len(fake.packets("FRC_Initialize")) == 2
    finally:
        fake.stop()


def test_after_an_alarm_reset_on_the_pendant_the_session_goes_on() -> None:
    fake = RmiFake(time_scale=0.05)
    host, port = fake.start("127.0.0.18", 0)
    try:
        with _robot(host, port) as r:
            r.move_joints(np.radians([5, -20, 15, 0, -45, 0]), 0.5)
            fake.raise_alarm("MOTN-017 Limit error (G:1^, A:1 hex)")
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([30, -20, 15, 0, -45, 0]), 0.5)
            assert "MOTN-017 Limit error" in _one_line(e, host, port)
            with pytest.raises(DeviceError) as e:  # the alarm still on
                r.move_joints(np.radians([30, -20, 15, 0, -45, 0]), 0.5)
            assert "move refused: the servo is not ready" in _one_line(e, host, port)
            fake.reset_on_pendant()
            for target in ([30, -20, 15, 0, -45, 0], [20, -20, 15, 0, -45, 0]):
                r.move_joints(np.radians(target), 0.5)
                np.testing.assert_allclose(fake.q_deg(), target, atol=1e-9)
        assert fake.sessions == 1
        assert fake.sequence_ids() == [1, 2, 1, 2]  # RMI aborted and initialised again
        assert len(fake.packets("FRC_Initialize")) == 2
    finally:
        fake.stop()


def test_the_idle_end_of_a_session_is_followed_by_a_new_one() -> None:
    fake = RmiFake(time_scale=0.01, idle_timeout_s=1.0)
    host, port = fake.start("127.0.0.18", 0)
    try:
        with _robot(host, port) as r:
            r.move_joints(np.radians([3, -20, 15, 0, -45, 0]), 0.5)
            _until(lambda: fake.terminated == 1, "no FRC_Terminate")
            _until(lambda: not fake.session_up, "the session was not closed")
            r.move_joints(np.radians([6, -20, 15, 0, -45, 0]), 0.5)
            np.testing.assert_allclose(np.degrees(r.actual_joints())[0], 6.0, atol=1e-3)
        assert fake.sessions == 2 and fake.terminated == 1
        assert fake.sequence_ids() == [1, 1]
    finally:
        fake.stop()


def test_stop_sends_abort_and_the_next_move_initialises_again() -> None:
    fake = RmiFake(time_scale=0.01)
    host, port = fake.start("127.0.0.17", 0)
    try:
        with _robot(host, port) as r:
            r.move_joints(np.radians([7, -20, 15, 0, -45, 0]), 0.5)
            assert not fake.packets("FRC_Abort")
            r.stop()
            _until(lambda: bool(fake.packets("FRC_Abort")), "no FRC_Abort")
            _until(lambda: not fake.rmi_running, "RMI still running")
            r.move_joints(np.radians([8, -20, 15, 0, -45, 0]), 0.5)
            np.testing.assert_allclose(np.degrees(r.actual_joints())[0], 8.0, atol=1e-3)
        assert fake.sequence_ids() == [1, 1]
        assert len(fake.packets("FRC_Initialize")) == 2
    finally:
        fake.stop()
