"""The UR twin driven by the unmodified ur_rtde (rtde_control, rtde_receive), raw RTDE
and dashboard clients on the wire, and the URRobot driver against the twin.

Every test binds its own loopback address (ur_rtde fixes the ports) and has a timeout
with the thread method: ur_rtde blocks in C++, where a SIGALRM handler cannot run."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Sequence

import numpy as np
import pytest

from cellcal.drivers.ur import URRobot
from cellcal.errors import DeviceError
from cellcal.mocks.ur.server import POLYSCOPE_VERSION
from tests.lazy import Rotation
from tests.mocks.test_ur_twin_wire import Rtde as RawRTDE
from tests.mocks.test_ur_twin_wire import dashboard
from tests.mocks.ur_clients import (
    KIN,
    Q0,
    Q1,
    clients,
    eventually,
    halted_joints,
    ur_twin,
    wait_for,
)

pytestmark = [pytest.mark.twin, pytest.mark.slow]

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")


def assert_pose_close(actual: object, expected: np.ndarray, atol: float = 1e-8) -> None:
    """Poses [x, y, z, rotation vector]: the same position and the same rotation (a
    rotation by π has two rotation vectors)."""
    a = np.asarray(actual, dtype=float)
    np.testing.assert_allclose(a[:3], expected[:3], atol=atol)
    R = Rotation.from_rotvec(a[3:]).as_matrix()
    np.testing.assert_allclose(R, Rotation.from_rotvec(expected[3:]).as_matrix(), atol=atol)


# -- kinematics ---------------------------------------------------------------------------


@pytest.mark.timeout(60, method="thread")
def test_the_cells_kinematics_in_ur_units_round_trip() -> None:
    # The controller's kinematics are the cell's nominal model (cellcal's own UR10e).
    rng = np.random.default_rng(7)
    for _ in range(10):
        q = Q0 + rng.uniform(-0.6, 0.6, 6)
        pose = KIN.fk(q)
        sol = KIN.ik(pose, q + rng.uniform(-0.05, 0.05, 6))
        assert sol is not None
        assert_pose_close(KIN.fk(sol), pose, atol=1e-9)
    assert KIN.ik(np.array([5.0, 0, 0, 0, 0, 0]), Q0) is None
    assert KIN.ik(np.array([np.nan, 0, 0, 0, 0, 0]), Q0) is None


# -- ur_rtde against the twin ------------------------------------------------------------


@pytest.mark.timeout(60, method="thread")
def test_receive_interface_reads_the_state() -> None:
    host = "127.0.0.20"
    with ur_twin(host):
        r = rtde_receive.RTDEReceiveInterface(host)
        try:
            np.testing.assert_allclose(r.getActualQ(), Q0, atol=1e-12)
            assert_pose_close(r.getActualTCPPose(), KIN.fk(Q0), atol=1e-12)
            assert r.getRuntimeState() == 1  # STOPPED: no control script yet
            assert r.getRobotMode() == 7
            assert r.getSafetyMode() == 1
            assert r.getSafetyStatusBits() == 1
            assert r.getJointMode() == [253] * 6
            assert len(r.getPayloadCog()) == 3
            assert not r.isProtectiveStopped()
            t0 = r.getTimestamp()
            wait_for(lambda: r.getTimestamp() > t0, "the timestamp to advance")
        finally:
            r.disconnect()


@pytest.mark.timeout(60, method="thread")
def test_receive_interface_unknown_variable_is_not_found() -> None:
    host = "127.0.0.21"
    with ur_twin(host), pytest.raises(RuntimeError, match="no_such_variable"):
        rtde_receive.RTDEReceiveInterface(host, variables=["actual_q", "no_such_variable"])


@pytest.mark.timeout(60, method="thread")
def test_control_movej_movel_ik_and_stop_script() -> None:
    host = "127.0.0.22"
    seen: list[np.ndarray] = []
    with ur_twin(host, on_move=seen.append) as sim, clients(host) as ur:
        assert ur.c.isProgramRunning()
        wait_for(lambda: ur.r.getRuntimeState() == 2, "runtime_state PLAYING")  # other link
        t0 = time.monotonic()
        assert ur.c.moveJ(Q1.tolist(), 1.0, 1.4)
        # time_scale 0: a few RTDE cycles, where the motion itself takes 1.1 s.
        assert time.monotonic() - t0 < 0.6
        np.testing.assert_allclose(sim.q, Q1, atol=1e-12)
        np.testing.assert_allclose(seen[-1], Q1, atol=1e-12)  # on_move before "done"
        eventually(lambda: np.testing.assert_allclose(ur.r.getActualQ(), Q1, atol=1e-12))
        assert_pose_close(ur.r.getActualTCPPose(), KIN.fk(Q1), atol=1e-12)

        target = KIN.fk(Q1 + np.array([0.05, 0.04, -0.03, 0.02, 0.05, -0.06]))
        assert ur.c.moveL(target.tolist(), 0.25, 1.2)
        eventually(lambda: assert_pose_close(ur.r.getActualTCPPose(), target))
        assert_pose_close(KIN.fk(np.array(ur.r.getActualQ())), target)

        assert ur.c.moveJ_IK(KIN.fk(Q0).tolist(), 1.0, 1.4)
        eventually(lambda: assert_pose_close(ur.r.getActualTCPPose(), KIN.fk(Q0)))

        # An unreachable pose ends the control script, as a runtime error does.
        assert not ur.c.moveL([5.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.25, 1.2)
        assert not ur.c.isProgramRunning()
        assert ur.c.reuploadScript()
        wait_for(lambda: ur.c.isProgramRunning(), "the control script to run again")
        assert ur.c.moveJ(Q0.tolist(), 1.0, 1.4)

        ur.c.stopScript()
        assert not ur.c.isProgramRunning()
        wait_for(lambda: ur.r.getRuntimeState() == 1, "runtime_state STOPPED")


@pytest.mark.timeout(60, method="thread")
def test_async_movej_reports_progress_and_stopj_ends_it() -> None:
    host = "127.0.0.23"
    with ur_twin(host, time_scale=0.25) as sim, clients(host) as ur:
        assert ur.c.getAsyncOperationProgress() < 0
        target = Q0 + 1.0  # 1 rad at 1 rad/s, 4 rad/s²: 1.25 s simulated, ~0.3 s wall
        t0 = time.monotonic()
        assert ur.c.moveJ(target.tolist(), 1.0, 4.0, True)
        assert time.monotonic() - t0 < 0.25  # returned before the move ended
        status = ur.c.getAsyncOperationProgressEx()
        assert status.isAsyncOperationRunning()
        assert ur.c.getAsyncOperationProgress() >= 0
        op = status.operationId()
        wait_for(lambda: ur.c.getAsyncOperationProgress() < 0, "the async move to end")
        assert not ur.c.getAsyncOperationProgressEx().isAsyncOperationRunning()
        assert ur.c.getAsyncOperationProgressEx().operationId() == op
        eventually(lambda: np.testing.assert_allclose(ur.r.getActualQ(), target, atol=1e-12))

        assert ur.c.moveJ(Q0.tolist(), 1.0, 4.0, True)
        wait_for(lambda: abs(sim.q[0] - target[0]) > 0.05, "the robot to move")
        ur.c.stopJ(2.0)
        assert not ur.c.getAsyncOperationProgressEx().isAsyncOperationRunning()
        q_stop = np.array(ur.r.getActualQ())
        assert np.max(np.abs(q_stop - Q0)) > 0.1  # stopped on the way
        assert ur.c.moveJ(Q0.tolist(), 1.0, 4.0)  # and ready for the next command
        eventually(lambda: np.testing.assert_allclose(ur.r.getActualQ(), Q0, atol=1e-12))


@pytest.mark.timeout(60, method="thread")
def test_protective_stop_fails_the_move_and_is_reported() -> None:
    host = "127.0.0.24"
    with ur_twin(host, time_scale=0.5) as sim, clients(host) as ur:
        result: list[bool] = []
        mover = threading.Thread(
            target=lambda: result.append(ur.c.moveJ((Q0 + 1.0).tolist(), 0.5, 1.4))
        )
        mover.start()
        wait_for(lambda: abs(sim.q[0] - Q0[0]) > 0.01, "the robot to move")
        sim.inject_protective_stop()
        mover.join(10)
        assert result == [False]
        # (ur_rtde 1.6.5 has isProtectiveStopped on the receive interface only)
        wait_for(lambda: ur.r.isProtectiveStopped(), "the protective stop on the receive link")
        assert ur.r.getSafetyStatusBits() & (1 << 2)
        assert ur.r.getSafetyMode() == 3
        # Where it halted: the stop bits go out at once, the joints a round trip later
        # (the receive link publishes a position once the twin's parent has acknowledged
        # it), so wait until both views agree and have stayed put for 0.1 s.
        q_stopped = halted_joints(sim, ur)
        assert 0.01 < q_stopped[0] - Q0[0] < 0.99
        assert dashboard(host, ["safetystatus"])[1] == "Safetystatus: PROTECTIVE_STOP"
        assert not ur.c.moveJ(Q0.tolist(), 1.0, 1.4)  # refused while stopped
        np.testing.assert_allclose(sim.q, q_stopped)

        assert dashboard(host, ["unlock protective stop"])[1] == "Protective stop releasing"
        wait_for(lambda: not ur.r.isProtectiveStopped(), "the protective stop to clear")
        # The control link may show the stop for a cycle longer: then moveJ says False.
        wait_for(lambda: ur.c.moveJ(Q0.tolist(), 3.0, 10.0), "a move after the unlock")
        eventually(lambda: np.testing.assert_allclose(ur.r.getActualQ(), Q0, atol=1e-12))


@pytest.mark.timeout(60, method="thread")
def test_reconnect_after_disconnect() -> None:
    host = "127.0.0.25"
    with ur_twin(host), clients(host) as ur:
        assert ur.c.moveJ(Q1.tolist(), 1.0, 1.4)
        ur.c.disconnect()
        ur.r.disconnect()
        assert not ur.r.isConnected()
        # The control script still runs: ur_rtde stops it (cmd 255, dashboard "stop")
        # and uploads it again.
        ur.c = rtde_control.RTDEControlInterface(host)
        assert ur.c.isProgramRunning()
        assert ur.r.reconnect()
        np.testing.assert_allclose(ur.r.getActualQ(), Q1, atol=1e-12)
        assert ur.c.moveJ(Q0.tolist(), 1.0, 1.4)
        eventually(lambda: np.testing.assert_allclose(ur.r.getActualQ(), Q0, atol=1e-12))


# -- the wire -----------------------------------------------------------------------------


@pytest.mark.timeout(60, method="thread")
def test_dashboard_request_reply_pairs() -> None:
    host = "127.0.0.26"
    with ur_twin(host):
        lines = [
            "PolyscopeVersion",
            "get serial number",
            "is in remote control",
            "robotmode",
            "safetystatus",
            "stop",
            "play",
            "power off",
            "robotmode",
            "power on",
            "brake release",
            "robotmode",
            "unlock protective stop",
            "close popup",
            "running",
            "frobnicate now",
        ]
        replies = dashboard(host, lines)
    assert replies[0] == "Connected: Universal Robots Dashboard Server"
    assert replies[1] == POLYSCOPE_VERSION == "URSoftware 5.11.1.108318 (Mar 22 2021)"
    assert replies[2].isdigit()
    assert replies[3:] == [
        "true",
        "Robotmode: RUNNING",
        "Safetystatus: NORMAL",
        "Failed to execute: stop",  # no program running
        "Failed to execute: play",  # no program loaded yet
        "Powering off",
        "Robotmode: POWER_OFF",
        "Powering on",
        "Brake releasing",
        "Robotmode: RUNNING",
        "Protective stop releasing",
        "closing popup",
        "Program running: false",
        "could not understand: 'frobnicate now'",
    ]


@pytest.mark.timeout(60, method="thread")
def test_rtde_wire_recipes_types_and_data() -> None:
    host = "127.0.0.27"
    with ur_twin(host):
        a = RawRTDE(host)
        b = RawRTDE(host)
        try:
            assert a.ask(ord("V"), struct.pack(">H", 2)) == b"\x01"
            assert struct.unpack(">IIII", a.ask(ord("v"))) == (5, 11, 1, 108318)
            body = a.ask(ord("O"), struct.pack(">d", 125.0) + b"actual_q,bogus_name")
            assert body[0] == 0 and body[1:] == b"VECTOR6D,NOT_FOUND"
            names = b"actual_q,runtime_state,robot_mode,joint_mode,actual_digital_input_bits,"
            names += b"payload_cog,safety_status_bits,"
            body = a.ask(ord("O"), struct.pack(">d", 125.0) + names)
            assert body[0] == 1
            assert body[1:] == b"VECTOR6D,UINT32,INT32,VECTOR6INT32,UINT64,VECTOR3D,UINT32"
            inputs = b"input_int_register_0,input_double_register_0"
            assert a.ask(ord("I"), inputs) == b"\x01INT32,DOUBLE"
            assert a.ask(ord("I"), b"input_int_register_0,external_force_torque,") == (
                b"\x02INT32,VECTOR6D"
            )
            assert a.ask(ord("I"), b"no_such_input") == b"\x03NOT_FOUND"
            # Recipe ids are per connection; registers owned by another are IN_USE.
            assert b.ask(ord("V"), struct.pack(">H", 2)) == b"\x01"
            assert b.ask(ord("I"), b"input_int_register_0") == b"\x01IN_USE"
            assert b.ask(ord("I"), b"input_int_register_5") == b"\x02INT32"

            assert a.ask(ord("S")) == b"\x01"
            mtype, data = a.recv()
            assert mtype == ord("U")
            fmt = ">B6dIi6iQ3dI"
            assert len(data) == struct.calcsize(fmt)
            fields = struct.unpack(fmt, data)
            assert fields[0] == 1
            np.testing.assert_allclose(fields[1:7], Q0)
            assert fields[7:9] == (1, 7)
            assert fields[9:15] == (253,) * 6
            assert fields[19] == 1
            a.send(ord("P"))
            while (msg := a.recv())[0] == ord("U"):  # packages already on their way
                pass
            assert msg == (ord("P"), b"\x01")
        finally:
            a.close()
            b.close()
        # Closing a connection frees its registers (once the server has seen it close).
        deadline = time.monotonic() + 5
        while True:
            c = RawRTDE(host)
            try:
                assert c.ask(ord("V"), struct.pack(">H", 2)) == b"\x01"
                if c.ask(ord("I"), b"input_int_register_0") == b"\x01INT32":
                    break
            finally:
                c.close()
            assert time.monotonic() < deadline, "registers still in use"


# -- the driver ---------------------------------------------------------------------------


@pytest.mark.timeout(60, method="thread")
def test_urrobot_moves_reads_and_closes() -> None:
    host = "127.0.0.30"
    seen: list[np.ndarray] = []
    with ur_twin(host, on_move=seen.append) as sim:
        robot = URRobot(host, name="arm", timeout_s=20)
        robot.connect()
        try:
            np.testing.assert_allclose(robot.actual_joints(), Q0, atol=1e-12)
            robot.move_joints(Q1, 0.5)
            np.testing.assert_allclose(robot.actual_joints(), Q1, atol=1e-12)
            np.testing.assert_allclose(sim.q, Q1, atol=1e-12)
            np.testing.assert_allclose(seen[-1], Q1, atol=1e-12)
            pose = robot.tcp_pose()
            ref = KIN.fk(Q1)
            assert_pose_close(np.concatenate([pose[:3] / 1000.0, pose[3:]]), ref, atol=1e-12)
            robot.stop()
            robot.move_joints(Q0, 1.0)
            # the move is done when the controller says so; the RTDE stream the driver
            # reads may be a cycle behind it (seen on a loaded machine)
            wait_for(
                lambda: np.allclose(robot.actual_joints(), Q0, rtol=0, atol=1e-12),
                "the RTDE stream to show the robot at Q0",
            )
        finally:
            robot.close()
        robot.close()  # twice is fine
        with pytest.raises(DeviceError, match=r"arm at 127\.0\.0\.30: not connected"):
            robot.move_joints(Q1, 0.5)
        robot.stop()  # a no-op when not connected
        assert dashboard(host, ["running"])[1] == "Program running: false"


@pytest.mark.timeout(60, method="thread")
def test_urrobot_protective_and_emergency_stop_are_device_errors() -> None:
    host = "127.0.0.31"
    with ur_twin(host, time_scale=0.5) as sim:
        robot = URRobot(host, timeout_s=20)
        robot.connect()
        try:
            errors: list[BaseException] = []

            def move() -> None:
                try:
                    robot.move_joints(Q0 + 1.0, 0.5)
                except BaseException as e:
                    errors.append(e)

            mover = threading.Thread(target=move)
            mover.start()
            wait_for(lambda: abs(sim.q[0] - Q0[0]) > 0.01, "the robot to move")
            sim.inject_protective_stop()
            mover.join(30)  # a loaded machine: the join waits, it asserts no time
            assert len(errors) == 1 and isinstance(errors[0], DeviceError)
            msg = str(errors[0])
            assert "\n" not in msg
            assert "127.0.0.31" in msg and "protective stop" in msg
            assert "did not complete" in msg

            with pytest.raises(DeviceError, match="protective stop; cannot move"):
                robot.move_joints(Q0, 1.0)
            sim.clear_protective_stop()
            # the driver reads the stop from RTDE: wait until its next packet says clear
            wait_for(lambda: not robot._receive.isProtectiveStopped(), "the stop to clear")
            _move_once_cleared(robot, Q0)
            # the move is done when the controller says so; the RTDE stream the driver
            # reads may be a cycle behind it (seen on a loaded machine)
            wait_for(
                lambda: np.allclose(robot.actual_joints(), Q0, rtol=0, atol=1e-12),
                "the RTDE stream to show the robot at Q0",
            )

            sim.inject_emergency_stop()
            # as with the protective stop: the driver learns of it from its next packet
            wait_for(lambda: robot._receive.isEmergencyStopped(), "the stop to be seen")
            with pytest.raises(DeviceError, match="emergency stop; cannot move"):
                robot.move_joints(Q1, 1.0)
            sim.clear_emergency_stop()
            wait_for(lambda: not robot._receive.isEmergencyStopped(), "the stop to clear")
            _move_once_cleared(robot, Q1)
        finally:
            robot.close()


def _move_once_cleared(robot: URRobot, q: Sequence[float]) -> None:
    """The move an operator makes after clearing a stop. The first one may be refused
    while the controller's move command after the stop is still settling (seen in two
    fresh-clone runs on a loaded machine: "the controller refused or aborted it"): one
    line, as the driver says; a second attempt within a few seconds must go through."""
    deadline = time.monotonic() + 5.0
    while True:
        try:
            robot.move_joints(np.asarray(q), 1.0)
            return
        except DeviceError as exc:
            if "refused or aborted" not in str(exc) or time.monotonic() > deadline:
                raise


@pytest.mark.timeout(60, method="thread")
def test_urrobot_timeout_and_busy() -> None:
    host = "127.0.0.32"
    with ur_twin(host, time_scale=1.0) as sim:
        robot = URRobot(host, timeout_s=1.0)
        robot.connect()
        try:
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match=r"moveJ timed out after 1 s"):
                robot.move_joints(Q0 + 1.0, 0.05)  # ~19 s at 0.0525 rad/s
            assert time.monotonic() - t0 < 3.0
            with pytest.raises(DeviceError, match="has not returned yet"):
                robot.move_joints(Q0, 1.0)
            sim.inject_protective_stop()  # ends the move in progress
        finally:
            robot.close()


@pytest.mark.timeout(60, method="thread")
def test_urrobot_unreachable_host() -> None:
    robot = URRobot("127.0.0.33", name="nobody", timeout_s=5)
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=r"nobody at 127\.0\.0\.33: cannot reach port 29999"):
        robot.connect()
    assert time.monotonic() - t0 < 2.0
    assert not robot.connected


@pytest.mark.timeout(60, method="thread")
def test_urrobot_validates_its_arguments() -> None:
    from cellcal.errors import InputError

    with pytest.raises(InputError):
        URRobot("127.0.0.34", velocity_rad_s=4.0)
    robot = URRobot("127.0.0.34")
    with pytest.raises(InputError):
        robot.move_joints(np.zeros(5), 0.5)
    with pytest.raises(InputError):
        robot.move_joints(np.zeros(6), 0.0)
    with pytest.raises(DeviceError, match="not connected"):
        robot.actual_joints()
