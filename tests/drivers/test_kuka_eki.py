"""The KUKA EthernetKRL driver against its twin over real sockets (127.0.0.180, .182,
.183): pinned telegrams, strict parsing, the move → settle → read contract, and the
faults — T1, drives off, a stop message, a program that never acknowledges, a second
client, a dropped link, a peer that is not cellcal's channel."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from cellcal.drivers.kuka_eki import KukaEkiOptions, KukaEkiRobot
from cellcal.drivers.kuka_eki_wire import (
    EkiCommand,
    EkiTelegramError,
    format_move,
    format_stop,
    parse_command,
    parse_state,
    split_telegrams,
)
from cellcal.errors import DeviceError
from cellcal.mocks.kuka.eki_server import EkiTwin
from tests.robot_controllers import krc

pytestmark = pytest.mark.timeout(60)

HOME = [0.0, -90.0, 90.0, 0.0, 0.0, 0.0]
STATE = (
    b'<CellCal><State Seq="7" Ack="6" Mode="#AUT" Drives="1" EStop="0" GuardStop="0" '
    b'InMotion="1" RobStopped="0" Program="#P_ACTIVE" StopMess="0"/>'
    b'<Axis A1="10.5" A2="-80.25" A3="85" A4="0.0" A5="1.0E+01" A6="-0.001"/></CellCal>'
)


def twin(host: str, **kw: object) -> tuple[EkiTwin, str, int]:
    server = EkiTwin(krc(HOME, **kw), cycle_s=0.01)  # type: ignore[arg-type]
    h, p = server.start(host, 0)
    return server, h, p


def robot(host: str, port: int) -> KukaEkiRobot:
    options = KukaEkiOptions(address=f"{host}:{port}", move_timeout_s=2.0, poll_s=0.002)
    return KukaEkiRobot(host, port, options=options)


def test_telegrams_are_pinned_and_parsed_strictly():
    s = parse_state(STATE)
    assert (s.seq, s.ack, s.mode, s.drives, s.in_motion) == (7, 6, "#AUT", True, True)
    assert s.axes_deg == (10.5, -80.25, 85.0, 0.0, 10.0, -0.001)
    assert format_move(8, 25, [10.5, -80.25, 85, 0, 30, 12]) == (
        b'<CellCal><Cmd Seq="8" Speed="25" A1="10.500000" A2="-80.250000" A3="85.000000" '
        b'A4="0.000000" A5="30.000000" A6="12.000000"/></CellCal>'
    )
    assert format_stop(8) == b'<CellCal><Stop Seq="8"/></CellCal>'
    assert parse_command(format_stop(3)) == EkiCommand(3)
    # two telegrams and a half in one read
    whole, rest = split_telegrams(STATE + b"\r\n" + STATE + b"<CellCal><St")
    assert len(whole) == 2 and rest == b"<CellCal><St"
    for bad, why in (
        (STATE.replace(b'Ack="6" ', b""), "<State> without Ack"),
        (STATE.replace(b'Drives="1"', b'Drives="yes"'), "Drives='YES': not 0, 1"),
        (STATE.replace(b'A6="-0.001"', b'A6="nan"'), "A6='nan': not a finite number"),
        (STATE.replace(b"<Axis", b"<Axes").replace(b"</CellCal>", b"</CellCal>"), "0 <Axis>"),
        (b'<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "b">]><CellCal/>', "DOCTYPE"),
        (b"<Robot/>", "root <Robot>"),
        (b"<CellCal><State", "not XML"),
    ):
        with pytest.raises(EkiTelegramError, match=why):
            parse_state(bad)
    with pytest.raises(EkiTelegramError, match="without </CellCal>"):
        split_telegrams(b"<CellCal>" + b" " * 5000)


def test_moves_settles_and_reads_the_measured_joints():
    server, host, port = twin("127.0.0.180", time_scale=0.02)
    try:
        with robot(host, port) as r:
            assert r.describe().family == "kuka-eki"
            np.testing.assert_allclose(np.degrees(r.actual_joints()), HOME, atol=1e-5)
            target = np.radians([10.5, -80.25, 85.0, 5.0, 30.0, 12.0])
            r.move_joints(target, 0.5)
            np.testing.assert_allclose(r.actual_joints(), target, atol=1e-6)
            np.testing.assert_allclose(np.radians(server.controller.q), target, atol=1e-9)
            assert server.controller.speed == 50
    finally:
        server.stop()


def test_faults_end_in_one_line_naming_the_robot():
    server, host, port = twin("127.0.0.182")
    c = server.controller
    try:
        c.faults.mode = "#T2"
        with pytest.raises(
            DeviceError, match=f"at 127.0.0.182:{port}: connect refused: controller in T2"
        ):
            robot(host, port).connect()
        c.faults.mode = "#EX"
        with robot(host, port) as r:
            # a second client: the channel takes one
            with pytest.raises(
                DeviceError, match="closed the connection at once: is another client"
            ):
                robot(host, port).connect()
            assert server.refused == 1
            c.faults.drives_on = False
            with pytest.raises(DeviceError, match=r"move (refused|failed): drives off"):
                r.move_joints(np.radians(HOME), 0.2)
            c.faults.drives_on = True
            with pytest.raises(DeviceError, match="move failed: a stop message is active"):
                r.move_joints(np.radians([0, -90, 170, 0, 0, 0]), 0.2)
            c.acknowledge_stop_message()
            c.faults.no_ack = True
            with pytest.raises(DeviceError, match=r"move not done after 2 s") as e:
                r.move_joints(np.radians([3, -90, 90, 0, 0, 0]), 0.2)
            assert "\n" not in str(e.value)
            c.faults.no_ack = False
            r.move_joints(np.radians(HOME), 0.2)
            # the link drops in the middle of a session
            server.stop()
            with pytest.raises(DeviceError, match=r"link lost|connection refused"):
                r.move_joints(np.radians([4, -90, 90, 0, 0, 0]), 0.2)
        with pytest.raises(DeviceError, match="connection refused: is CellCalEki running"):
            robot(host, port).connect()
    finally:
        server.stop()


def test_a_peer_that_is_not_the_channel_is_one_line():
    listener = socket.create_server(("127.0.0.183", 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.sendall(b"<Robot><Status ok='1'/></Robot>")
            conn.recv(16)

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        with pytest.raises(
            DeviceError,
            match="not a CellCalEki state telegram: bytes that do not start a <CellCal>",
        ):
            robot("127.0.0.183", port).connect()
    finally:
        thread.join(5)
        listener.close()
