"""The FANUC RMI driver against its twin over real sockets (127.0.0.13, .14, .15):
pinned packet fields, the session (the connection port naming the session's port),
consecutive sequence ids whose answer is the move's acknowledgement, and the faults —
the teach pendant enabled, the servo off, an alarm during the move, a second client, a
wrong sequence id, the 60-minute idle end of a session, a stop, a peer that is not RMI."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from cellcal.drivers import fanuc_rmi_wire as wire
from cellcal.drivers.fanuc_rmi import FanucRmiOptions, FanucRmiRobot
from cellcal.errors import DeviceError
from cellcal.mocks.fanuc.rmi_server import RmiTwin
from tests.robot_controllers import krc

pytestmark = pytest.mark.timeout(60)

HOME = [0.0, -90.0, 90.0, 0.0, 0.0, 0.0]


def twin(host: str, **kw: object) -> tuple[RmiTwin, int]:
    idle_s = float(kw.pop("idle_s", 3600.0))  # type: ignore[arg-type]
    server = RmiTwin(krc(HOME, time_scale=0.01, **kw), idle_s=idle_s, time_scale=1.0)
    _, port = server.start(host, 0)
    return server, port


def robot(host: str, port: int, **options: object) -> FanucRmiRobot:
    o = FanucRmiOptions(address=f"{host}:{port}", move_timeout_s=3.0, **options)  # type: ignore[arg-type]
    return FanucRmiRobot(host, port, options=o)


def session(twin: RmiTwin) -> list[tuple[str, str]]:
    return [wire.name_of(p) for p in twin.received]


def test_packets_are_pinned_and_read_by_field():
    move = wire.joint_motion(3, [10.5, -80.25, 85, 0, 30, 12], 25)
    assert json.loads(wire.encode(move)) == {
        "Instruction": "FRC_JointMotionJRep",
        "SequenceID": 3,
        "JointAngle": {
            "J1": 10.5, "J2": -80.25, "J3": 85.0, "J4": 0.0, "J5": 30.0, "J6": 12.0,
            "J7": 0.0, "J8": 0.0, "J9": 0.0,
        },
        "SpeedType": "Percent",
        "Speed": 25,
        "TermType": "FINE",
        "TermValue": 0,
    }  # fmt: skip
    assert wire.encode(wire.connect()) == b'{"Communication":"FRC_Connect"}\r\n'
    status = wire.status_of(
        {"Command": "FRC_GetStatus", "ErrorID": 0, "ServoReady": 1, "TPMode": 0.0,
         "RMIMotionStatus": 1, "ProgramStatus": 1, "SingleStepMode": 0, "NumberUTool": 1,
         "NextSequenceID": 8, "NumberUFrame": 0, "Override": 100}
    )  # fmt: skip
    assert (status.servo_ready, status.tp_enabled, status.rmi_running) == (True, False, True)
    assert status.next_sequence == 8
    lines, rest = wire.split_lines(b'{"Command":"FRC_Abort","ErrorID":0}\r\n\r\n{"Comm')
    assert [wire.decode(x)["Command"] for x in lines] == ["FRC_Abort"] and rest == b'{"Comm'
    for bad, why in (
        (b"GET / HTTP/1.1", "not a JSON line"),
        (b"[1, 2]", "not a JSON object"),
        (b'{"ErrorID": 0, "Command": "FRC_Abort"}', "no Communication, Command or Instruction"),
    ):
        with pytest.raises(wire.RmiPacketError, match=why):
            wire.decode(bad)
    with pytest.raises(wire.RmiPacketError, match=r"TPMode = 0\.5 is not an integer"):
        wire.status_of({"Command": "FRC_GetStatus", "ServoReady": 1, "TPMode": 0.5})
    assert wire.error_text(2556957) == "ErrorID 2556957 (invalid sequence id)"


def test_a_session_moves_with_consecutive_sequence_ids_and_reads_after_the_answer():
    server, port = twin("127.0.0.13")
    try:
        with robot("127.0.0.13", port, uframe=2, utool=3) as r:
            assert r.describe().maker == "FANUC" and r.describe().firmware == "RMI 1.0"
            np.testing.assert_allclose(r.actual_joints(), np.radians(HOME), atol=1e-6)
            for k in range(3):
                target = np.radians(HOME) + np.radians([5.0 * (k + 1), -4, 6, 3, -5, 10])
                r.move_joints(target, 0.4)
                np.testing.assert_allclose(r.actual_joints(), target, atol=1e-5)
        names = session(server)
        assert names[:4] == [
            ("Command", "FRC_GetStatus"),
            ("Command", "FRC_Reset"),
            ("Command", "FRC_Initialize"),
            ("Command", "FRC_GetUFrameUTool"),
        ]
        assert names[-1] == ("Communication", "FRC_Disconnect")
        moves = [p for p in server.received if p.get("Instruction") == "FRC_JointMotionJRep"]
        assert [m["SequenceID"] for m in moves] == [1, 2, 3]
        assert {(m["Speed"], m["TermType"], m["SpeedType"]) for m in moves} == {
            (40, "FINE", "Percent")
        }
        # the joints are read after each move's answer, never the set-point
        after = [names[i + 1] for i, p in enumerate(server.received) if p in moves]
        assert set(after) == {("Command", "FRC_ReadJointAngles")}
        assert (server.state.uframe, server.state.utool) == (2, 3)
        init = next(p for p in server.received if p.get("Command") == "FRC_Initialize")
        assert init["GroupMask"] == 1
    finally:
        server.stop()


@pytest.mark.parametrize(
    ("fault", "says"),
    [
        ("tp_enabled", "the teach pendant is enabled"),
        ("servo_off", "the servo is not ready"),
        ("single_step", "single step mode"),
    ],
)
def test_a_controller_that_cannot_move_is_refused_in_one_line(fault: str, says: str):
    server, port = twin("127.0.0.14")
    setattr(server.faults, fault, True)
    try:
        with pytest.raises(DeviceError) as err:
            robot("127.0.0.14", port).connect()
        line = str(err.value)
        assert line.startswith(f"fanuc-robot at 127.0.0.14:{port}: connect refused: ")
        assert says in line and "\n" not in line
    finally:
        server.stop()


def test_an_alarm_during_the_move_names_the_controllers_text_and_a_new_session_resets_it():
    server, port = twin("127.0.0.13")
    try:
        r = robot("127.0.0.13", port)
        r.connect()
        target = np.radians(HOME)
        target[0] = np.radians(170.0)  # beyond the controller's ±155°
        with pytest.raises(DeviceError, match=r"system fault during the move \(sequence 1\): "
                           r"MOTN-017 Limit error .*; reset the alarm"):  # fmt: skip
            r.move_joints(target, 0.5)
        with pytest.raises(DeviceError, match="the servo is not ready"):
            r.move_joints(np.radians(HOME), 0.5)
        r.close()
        with robot("127.0.0.13", port) as again:  # a new session resets the alarm
            goal = np.radians(HOME) + 0.05
            again.move_joints(goal, 0.5)
            np.testing.assert_allclose(again.actual_joints(), goal, atol=1e-5)
    finally:
        server.stop()


def test_one_client_at_a_time_and_a_wrong_sequence_id_is_named():
    server, port = twin("127.0.0.15")
    try:
        with robot("127.0.0.15", port) as first:
            with pytest.raises(DeviceError, match=r"connect refused: ErrorID 2556954 \(the "
                               r"robot is already connected"):  # fmt: skip
                robot("127.0.0.15", port, request_timeout_s=0.5).connect()
            first.move_joints(np.radians(HOME) + 0.02, 0.5)
            first._seq = 7  # as if the driver had lost count
            with pytest.raises(DeviceError, match=r"move \(sequence 7\) refused: ErrorID "
                               r"2556957 \(invalid sequence id\)"):  # fmt: skip
                first._send_move(np.degrees(np.radians(HOME)), 0.5, 7)
            first.move_joints(np.radians(HOME), 0.5)  # the controller's NextSequenceID, 2
        moves = [p["SequenceID"] for p in server.received if "Instruction" in p]
        assert moves == [1, 7, 2]
    finally:
        server.stop()


def test_a_session_the_controller_ended_after_its_idle_time_is_opened_again():
    server, port = twin("127.0.0.14", idle_s=0.3)
    try:
        with robot("127.0.0.14", port) as r:
            deadline = time.monotonic() + 10
            while server._busy.locked():  # the twin sends FRC_Terminate and closes
                assert time.monotonic() < deadline
                time.sleep(0.02)
            goal = np.radians(HOME) + 0.03
            r.move_joints(goal, 0.5)
            np.testing.assert_allclose(r.actual_joints(), goal, atol=1e-5)
        assert session(server).count(("Command", "FRC_Initialize")) == 2
    finally:
        server.stop()


def test_stop_aborts_and_the_next_move_initialises_again():
    server, port = twin("127.0.0.15")
    try:
        with robot("127.0.0.15", port) as r:
            r.move_joints(np.radians(HOME) + 0.02, 0.5)
            r.stop()
            assert not server.state.running
            r.move_joints(np.radians(HOME), 0.5)
        names = session(server)
        assert names.count(("Command", "FRC_Initialize")) == 2
        moves = [p["SequenceID"] for p in server.received if "Instruction" in p]
        assert moves == [1, 1]
    finally:
        server.stop()


def test_nothing_listening_silence_and_a_peer_that_is_not_rmi_are_one_line():
    with pytest.raises(DeviceError, match=r"at 127\.0\.0\.14:1: connection to port 1 refused"):
        robot("127.0.0.14", 1).connect()
    for reply, says in ((b"HTTP/1.1 400 Bad Request\r\n", "not RMI"), (b"", "no answer")):
        listener = socket.create_server(("127.0.0.14", 0))
        listener.settimeout(10)
        port = listener.getsockname()[1]

        def peer(listener: socket.socket = listener, reply: bytes = reply) -> None:
            conn, _ = listener.accept()
            with conn:
                conn.recv(4096)
                if reply:
                    conn.sendall(reply)
                conn.recv(4096)

        thread = threading.Thread(target=peer, daemon=True)
        thread.start()
        r = robot("127.0.0.14", port, request_timeout_s=0.5)
        with pytest.raises(DeviceError, match=says) as err:
            r.connect()
        assert "\n" not in str(err.value)
        listener.close()
        thread.join(5)
