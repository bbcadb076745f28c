"""The KUKA driver (KUKAVARPROXY and the KRL loop) against its twin over real sockets
(127.0.0.170–.175): pinned bytes, KRL text, the move → settle → read contract, and the
faults a cell meets — T1, drives off, a stop message, a loop that never acknowledges,
another client, a dropped link, nothing listening."""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest

from cellcal.drivers.kuka_kvp import KukaKvpOptions, KukaKvpRobot
from cellcal.drivers.kuka_kvp_wire import (
    KrlTextError,
    decode_request,
    encode_reply,
    encode_request,
    format_axes,
    parse_axes,
    parse_bool,
    parse_int,
)
from cellcal.errors import DeviceError, InputError
from cellcal.mocks.kuka.kvp_server import KvpTwin
from tests.robot_controllers import krc

pytestmark = pytest.mark.timeout(60)

HOME = [0.0, -90.0, 90.0, 0.0, 0.0, 0.0]


def twin(host: str, **kw: object) -> tuple[KvpTwin, str, int]:
    server = KvpTwin(krc(HOME, **kw))  # type: ignore[arg-type]
    h, p = server.start(host, 0)
    return server, h, p


def robot(host: str, port: int, **kw: object) -> KukaKvpRobot:
    options = KukaKvpOptions(address=f"{host}:{port}", move_timeout_s=2.0, poll_s=0.002, **kw)  # type: ignore[arg-type]
    return KukaKvpRobot(host, port, options=options)


# ------------------------------------------------------------------ bytes and text


def test_the_published_read_request_bytes():
    """The spec's example read of $AXIS_ACT_MEAS, byte for byte."""
    expected = bytes.fromhex("0001 0011 00 000e 24415849535f4143545f4d454153".replace(" ", ""))
    assert encode_request(1, 0, "$AXIS_ACT_MEAS") == expected
    assert decode_request(expected[4:]) == (0, "$AXIS_ACT_MEAS", None)


def test_write_request_and_replies_are_pinned():
    assert encode_request(0x0203, 1, "CC_SEQ", "17") == bytes.fromhex(
        "0203 000d 01 0006 43435f534551 0002 3137".replace(" ", "")
    )
    assert encode_reply(7, 0, b"TRUE", True) == bytes.fromhex(
        "0007 000a 00 0004 54525545 0001 01".replace(" ", "")
    )
    # a failed request: value length 0, no value, ok 0
    assert encode_reply(7, 0, b"ignored", False) == bytes.fromhex(
        "0007 0006 00 0000 0001 00".replace(" ", "")
    )


def test_krl_axis_text_parsed_strictly():
    text = "{E6AXIS: A1 -39.86, A2 -91.2500, A3 1.0E+02, A4 0.0, A5 45.5, A6 -0.001, E1 0.0, E2 0.0, E3 0.0, E4 0.0, E5 0.0, E6 0.0}"  # noqa: E501
    assert parse_axes(text, "$AXIS_ACT_MEAS") == [-39.86, -91.25, 100.0, 0.0, 45.5, -0.001]
    assert parse_axes("{A1 1, A2 2, A3 3, A4 4, A5 5, A6 6}", "x") == [1, 2, 3, 4, 5, 6]
    assert parse_axes(format_axes([1.5, -2, 3, 4, 5, 6]), "x") == [1.5, -2, 3, 4, 5, 6]
    for bad, why in (
        ("{E6POS: X 1, Y 2}", "a E6POS"),
        ("{E6AXIS: A1 1, A2 2, A3 3, A4 4, A5 5}", "no A6"),
        ("{E6AXIS: A1 1, A2 2, A3 3, A4 4, A5 5, A6 x}", "'x' is not a KRL REAL"),
        ("{E6AXIS: A1 1, A1 2, A3 3, A4 4, A5 5, A6 6}", "A1 given twice"),
        ("{E6AXIS: A1 1, A2 2, A3 3, A4 4, A5 5, A7 6}", "'A7' is not a component"),
        ("E6AXIS: A1 1", "not a KRL structure"),
        ("{E6AXIS: A1 nan, A2 2, A3 3, A4 4, A5 5, A6 6}", "not a KRL REAL"),
    ):
        with pytest.raises(KrlTextError, match=why):
            parse_axes(bad, "$AXIS_ACT_MEAS")
    assert parse_int(" 17 ", "CC_SEQ") == 17 and parse_bool("true", "$PERI_RDY") is True
    with pytest.raises(KrlTextError, match=r"CC_SEQ: '1\.5' is not a KRL INT"):
        parse_int("1.5", "CC_SEQ")


# ------------------------------------------------------------------ the contract


def test_moves_settles_and_reads_the_measured_joints():
    server, host, port = twin("127.0.0.170", time_scale=0.02)
    try:
        with robot(host, port) as r:
            assert r.describe().maker == "KUKA" and r.robot_name == "KR5ARC"
            np.testing.assert_allclose(np.degrees(r.actual_joints()), HOME, atol=1e-5)
            target = np.radians([10.5, -80.25, 85.0, 5.0, 30.0, 12.0])
            r.move_joints(target, 0.5)
            np.testing.assert_allclose(r.actual_joints(), target, atol=1e-6)
            r.move_joints(np.radians(HOME), 1.0)
        writes = [(name, value) for f, name, value in server.controller.requests if f == 1]
        # target, speed, then the sequence that starts the move
        # a stale stop cleared, the target, the speed, then the sequence that starts it
        assert [n for n, _ in writes[:4]] == ["CC_STOP", "CC_TARGET", "CC_SPEED", "CC_SEQ"]
        assert writes[0][1] == "FALSE" and writes[2][1] == "50" and writes[3][1] == "1"
        assert writes[7][1] == "2"
        assert parse_axes(writes[1][1], "CC_TARGET") == pytest.approx([10.5, -80.25, 85, 5, 30, 12])
    finally:
        server.stop()


@pytest.mark.parametrize(
    ("faults", "expected"),
    [
        ({"mode": "#T1"}, "controller in T1: the KRL loop runs unattended in AUT or EXT only"),
        ({"drives_on": False}, r"drives off \(\$PERI_RDY FALSE\)"),
    ],
)
def test_a_controller_that_cannot_move_is_refused_at_connect(faults, expected):
    server, host, port = twin("127.0.0.171", **faults)
    try:
        r = robot(host, port)
        with pytest.raises(
            DeviceError, match=f"robot at 127.0.0.171:{port}: connect refused: {expected}"
        ):
            r.connect()
    finally:
        server.stop()


def test_faults_during_a_campaign_end_in_one_line_naming_the_robot():
    server, host, port = twin("127.0.0.172")
    c = server.controller
    try:
        with robot(host, port) as r:
            # a target beyond the controller's limits: a stop message, the move refused
            with pytest.raises(DeviceError, match=r"move failed: a stop message is active") as e:
                r.move_joints(np.radians([0, -90, 170, 0, 0, 0]), 0.2)
            assert "\n" not in str(e.value) and f"127.0.0.172:{port}" in str(e.value)
            c.acknowledge_stop_message()
            # the loop hangs: not acknowledged within the timeout, a stop is sent
            c.faults.no_ack = True
            with pytest.raises(DeviceError, match=r"move not done after 2 s \(sequence \d+"):
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.2)
            assert c.requests[-1][:2] == (1, "CC_STOP")
            c.faults.no_ack = False
            # switched to T1 between moves
            c.faults.mode = "#T1"
            with pytest.raises(DeviceError, match="move refused: controller in T1"):
                r.move_joints(np.radians(HOME), 0.2)
            c.faults.mode = "#AUT"
            r.move_joints(np.radians(HOME), 0.2)
            # an unknown variable is named
            with pytest.raises(DeviceError, match=r"reading \$NOPE failed: no such variable"):
                r.read("$NOPE")
    finally:
        server.stop()


def test_another_client_commanding_the_loop_is_named():
    server, host, port = twin("127.0.0.173", time_scale=1.0)
    try:
        with robot(host, port) as r, socket.create_connection((host, port), timeout=5) as other:
            done = threading.Event()

            def intrude() -> None:
                # while our move runs (about 0.3 s), another client writes CC_SEQ
                while not done.is_set() and server.controller.move is None:
                    done.wait(0.002)
                other.sendall(encode_request(9, 1, "CC_SEQ", "4242"))
                other.recv(256)

            thread = threading.Thread(target=intrude)
            thread.start()
            try:
                with pytest.raises(DeviceError, match="another client wrote CC_SEQ = 4242"):
                    r.move_joints(np.radians([40, -90, 90, 0, 0, 0]), 1.0)
            finally:
                done.set()
                thread.join()
    finally:
        server.stop()


def test_a_dropped_link_and_nothing_listening():
    server, host, port = twin("127.0.0.174")
    r = robot(host, port)
    r.connect()
    server.stop()
    with pytest.raises(
        DeviceError, match=f"robot at 127.0.0.174:{port}: (link lost|connection refused)"
    ):
        r.move_joints(np.radians(HOME), 0.2)
    r.close()
    with pytest.raises(DeviceError, match="connection refused: is KUKAVARPROXY running"):
        robot(host, port).connect()


def _dropped(server: KvpTwin, n: int) -> None:
    """Wait until the twin has dropped ``n`` idle clients."""
    deadline = time.monotonic() + 10.0
    while server.dropped_idle < n:
        assert time.monotonic() < deadline, "the twin never dropped the idle client"
        time.sleep(0.02)


def test_an_idle_link_is_opened_afresh_before_the_proxy_drops_it():
    """KUKAVARPROXY drops a client that has sent nothing for its idle timeout (60 s; the
    twin here 0.3 s): a driver whose link stood idle longer than ``idle_reopen_s`` opens it
    afresh before its next request. One that does not sends into the dropped socket."""
    server = KvpTwin(krc(HOME, time_scale=0.02), idle_timeout_s=0.3)  # type: ignore[arg-type]
    host, port = server.start("127.0.0.174", 0)
    try:
        r = robot(host, port, idle_reopen_s=0.1)
        r.connect()
        r.move_joints(np.radians(HOME), 0.2)
        _dropped(server, 1)  # the proxy has let the silent client go
        r.move_joints(np.radians([1.0, -90.0, 90.0, 0.0, 0.0, 0.0]), 0.2)
        r.close()
        stale = robot(host, port, idle_reopen_s=3600.0)
        stale.connect()
        _dropped(server, 2)
        with pytest.raises(DeviceError, match=f"robot at {host}:{port}: link lost"):
            stale.move_joints(np.radians(HOME), 0.2)
        stale.close()
    finally:
        server.stop()


def test_bytes_that_are_not_kukavarproxy_are_one_line():
    """A server that answers with an HTTP page instead of the proxy's frames."""
    listener = socket.create_server(("127.0.0.175", 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.recv(256)
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        with pytest.raises(DeviceError, match="not a KUKAVARPROXY reply"):
            robot("127.0.0.175", port).connect()
    finally:
        thread.join(5)
        listener.close()


def test_options_are_checked():
    with pytest.raises(ValueError, match="target_var"):
        KukaKvpOptions(target_var="CC TARGET; $OV_PRO")
    r = robot("127.0.0.175", 1)
    with pytest.raises(InputError, match="target must be 6 finite joint angles"):
        r.move_joints(np.array([0.0, math.nan, 0, 0, 0, 0]), 0.2)
