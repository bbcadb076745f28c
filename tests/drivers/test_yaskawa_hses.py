"""The Yaskawa HSES driver against its twin over real UDP sockets (127.0.0.54, .55, .56):
pinned datagram bytes, pulses per degree at the boundary, the servo turned on, a move
done when the controller no longer runs and stands at the target, lost datagrams sent
again and duplicate answers dropped, and the faults — TEACH, no command remote, a servo
that cannot come on, an alarm during the move, nothing listening, silence, a peer that
is not HSES, and impossible pulses per degree in the configuration."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from cellcal.config import config_from_dict
from cellcal.drivers import yaskawa_hses_wire as wire
from cellcal.drivers.yaskawa_hses import YaskawaHsesOptions, YaskawaHsesRobot
from cellcal.errors import ConfigError, DeviceError
from cellcal.mocks.yaskawa.hses_server import HsesTwin
from tests.drivers.families import bundled_cells
from tests.robot_controllers import krc

pytestmark = pytest.mark.timeout(60)

HOME = [0.0, -60.0, 60.0, 0.0, 30.0, 0.0]
PPD = [1434.6, 1434.6, 1227.8, 807.6, 807.6, 474.2]


def twin(host: str, **faults: object) -> tuple[HsesTwin, int]:
    server = HsesTwin(krc(HOME, time_scale=0.01), PPD)
    for key, value in faults.items():
        setattr(server.faults, key, value)
    _, port = server.start(host, 0)
    return server, port


def robot(host: str, port: int, **options: object) -> YaskawaHsesRobot:
    o = YaskawaHsesOptions(
        address=f"{host}:{port}",
        pulses_per_degree=PPD,
        move_timeout_s=5.0,
        request_timeout_s=0.2,
        poll_s=0.005,
        **options,  # type: ignore[arg-type]
    )
    return YaskawaHsesRobot(host, port, options=o)


def test_datagrams_are_pinned():
    status = wire.encode_request(wire.Request(wire.STATUS, 1, 0, wire.GET_ALL, 7))
    assert status == (
        b"YERC\x20\x00\x00\x00\x03\x01\x00\x07\x00\x00\x00\x00"
        b"99999999"
        b"\x72\x00\x01\x00\x00\x01\x00\x00"
    )
    move = wire.pulse_move(1, 2500, [1000, -2000, 3000, 0, 50, -60])
    assert len(move) == 88
    assert struct.unpack("<22i", move) == (
        1, 0, 0, 2500, 1000, -2000, 3000, 0, 50, -60, 0, 0, 0, *[0] * 9
    )  # fmt: skip
    answer = wire.encode_answer(wire.Answer(7, 0x81, 0x1F, 0x2070, b""))
    assert answer[8:16] == b"\x03\x01\x01\x07\x00\x00\x00\x80"
    assert answer[24:32] == b"\x81\x1f\x01\x00\x70\x20\x00\x00"  # fs100's layout
    got = wire.decode_answer(answer)
    assert (got.request_id, got.status, got.added) == (7, 0x1F, 0x2070)
    assert got.reason == "status 0x1F, added status 0x2070 (servo off)"
    s = wire.status_of(struct.pack("<II", 0xC4 | 0x08, 0x40))
    assert (s.play, s.remote, s.running, s.servo_on, s.teach, s.alarm) == (
        True, True, True, True, False, False
    )  # fmt: skip
    for bad, why in (
        (b"YERC", "shorter than the 32-byte header"),
        (b"HTTP" + answer[4:], "no YERC header"),
        (answer[:10] + b"\x00" + answer[11:], "not an answer"),
        (answer + b"x", "data size 0 but 1 bytes follow"),
    ):
        with pytest.raises(wire.HsesPacketError, match=why):
            wire.decode_answer(bad)


def test_the_servo_is_turned_on_moves_settle_and_pulses_become_degrees():
    server, port = twin("127.0.0.54")
    try:
        with robot("127.0.0.54", port) as r:
            assert server.servo_on and r.describe().maker == "Yaskawa"
            np.testing.assert_allclose(np.degrees(r.actual_joints()), HOME, atol=1e-3)
            target = np.radians([10.0, -45.5, 72.25, -30.0, 20.0, 90.0])
            r.move_joints(target, 0.4)
            # within a pulse: 1/474.2 deg on axis 6
            np.testing.assert_allclose(np.degrees(r.actual_joints()), np.degrees(target), atol=3e-3)
        moves = [q for q in server.requests if q.command == wire.PULSE_MOVE]
        m = wire.pulse_move_of(moves[0].data)
        assert (m.robot, m.station, m.speed_class, m.speed) == (1, 0, 0, 4000)
        assert m.pulses[:6] == tuple(round(d * p) for d, p in zip(
            [10.0, -45.5, 72.25, -30.0, 20.0, 90.0], PPD, strict=True))  # fmt: skip
        servo = [q for q in server.requests if q.command == wire.HOLD_SERVO]
        assert [(q.instance, wire.word_of(q.data)) for q in servo] == [(wire.SERVO, wire.ON)]
    finally:
        server.stop()


def test_lost_datagrams_are_sent_again_and_duplicate_answers_dropped():
    server, port = twin("127.0.0.55", lose_every=4, duplicate_every=3)
    try:
        with robot("127.0.0.55", port, retries=3) as r:
            for k in range(4):
                goal = np.radians(HOME) + np.radians([3.0 * (k + 1), -2, 2, 5, -3, 8])
                r.move_joints(goal, 0.5)
                np.testing.assert_allclose(r.actual_joints(), goal, atol=1e-4)
            assert r.resent >= server.lost > 0 and server.duplicated > 0
            # the last answer's copy may still be unread: read on, faults off, for ≤ 2 s
            server.faults.lose_every = server.faults.duplicate_every = 0
            deadline = time.monotonic() + 2.0
            while r.dropped < server.duplicated and time.monotonic() < deadline:
                r.actual_joints()
            assert r.dropped >= server.duplicated
    finally:
        server.stop()


@pytest.mark.parametrize(
    ("fault", "says"),
    [
        ({"teach": True}, "connect refused: the controller is in TEACH"),
        ({"remote": False}, "connect refused: command remote is not set"),
        ({"servo_locked": True}, r"servo on refused: status 0x1F, added status 0x3450"),
    ],
)
def test_a_controller_that_cannot_move_is_refused_in_one_line(fault: dict, says: str):
    server, port = twin("127.0.0.56", **fault)
    try:
        with pytest.raises(DeviceError, match=says) as err:
            robot("127.0.0.56", port).connect()
        assert str(err.value).startswith(f"yaskawa-robot at 127.0.0.56:{port}: ")
        assert "\n" not in str(err.value)
    finally:
        server.stop()


def test_an_alarm_during_the_move_names_it_and_the_next_connection_resets_it():
    server, port = twin("127.0.0.54")
    try:
        r = robot("127.0.0.54", port)
        r.connect()
        beyond = np.radians(HOME)
        beyond[0] = np.radians(170.0)  # the controller's limit is ±155°
        with pytest.raises(DeviceError, match=r"move failed: alarm 4101 \(LIMIT AXIS 1"):
            r.move_joints(beyond, 0.5)
        r.close()
        with robot("127.0.0.54", port) as again:  # connect resets the alarm
            goal = np.radians(HOME) + 0.05
            again.move_joints(goal, 0.5)
            np.testing.assert_allclose(again.actual_joints(), goal, atol=1e-4)
        resets = [q.instance for q in server.requests if q.command == wire.RESET]
        assert resets == [wire.ALARM_RESET]
    finally:
        server.stop()


def test_stop_holds_and_the_next_move_releases_the_hold():
    server, port = twin("127.0.0.55")
    try:
        with robot("127.0.0.55", port) as r:
            r.stop()
            assert server.hold
            goal = np.radians(HOME) - 0.03
            r.move_joints(goal, 0.5)
            np.testing.assert_allclose(r.actual_joints(), goal, atol=1e-4)
            assert not server.hold
    finally:
        server.stop()


def test_nothing_listening_silence_and_a_peer_that_is_not_hses_are_one_line():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as free:
        free.bind(("127.0.0.56", 0))
        port = free.getsockname()[1]
    with pytest.raises(DeviceError, match="ICMP port unreachable"):
        robot("127.0.0.56", port).connect()
    for reply, says in ((b"", r"no answer to command 0x72 in 2 tries"), (b"hello", "not an HSES")):
        peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.bind(("127.0.0.56", 0))
        peer.settimeout(5)

        def answer(peer: socket.socket = peer, reply: bytes = reply) -> None:
            _, client = peer.recvfrom(2048)
            if reply:
                peer.sendto(reply, client)

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        with pytest.raises(DeviceError, match=says) as err:
            robot("127.0.0.56", peer.getsockname()[1], retries=1).connect()
        assert "\n" not in str(err.value)
        thread.join(5)
        peer.close()


@pytest.mark.parametrize(
    ("ppd", "says"),
    [
        (None, r"robot\.pulses_per_degree: .*required"),
        ([1000.0] * 5, "one value per axis: 6, got 5"),
        ([1000.0, 1000.0, 0.0, 1000.0, 1000.0, 1000.0], "axis 3: 0.0 is not a number of pulses"),
        ([1000.0] * 5 + [float("nan")], r"pulses_per_degree\.5: Input should be a finite number"),
    ],
)
def test_missing_or_impossible_pulses_per_degree_are_one_line(ppd: list | None, says: str):
    data = bundled_cells()[0].model_dump()
    data["robot"] = {"model": "kuka-kr5-arc", "driver": "yaskawa-hses", "address": "10.0.0.2"}
    if ppd is not None:
        data["robot"]["pulses_per_degree"] = ppd
    with pytest.raises(ConfigError, match=says) as err:
        config_from_dict(data, "cell.toml")
    assert "\n" not in str(err.value)
