"""cellcal's Yaskawa HSES driver against a fake controller written by another hand from
docs/robots.md and the header and data layouts of the open client hsinkoyu/fs100 alone
(tests/fakes/hses_fake.py, not from cellcal's twin), over real UDP sockets on
127.0.0.58–.59: the servo, moves landing on their pulses, refusals, an alarm mid-move, lost,
repeated and stale datagrams, and the hold. The fake answers with block number 0x80000000
and padding bytes 0x5A, sets its running bit late (or never, for a short move), jitters a
standing position by a pulse and lets the servo come on only a while after it is asked;
the twin does none of these."""

from __future__ import annotations

import itertools
import re
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import numpy as np
import pytest

from cellcal.drivers.yaskawa_hses import YaskawaHsesOptions, YaskawaHsesRobot
from cellcal.errors import DeviceError
from tests.fakes.hses_fake import HsesFake

pytestmark = pytest.mark.timeout(60)

PPD = [1434.6, 1434.6, 1227.8, 807.6, 807.6, 474.2]
HOME = [0.0, -90.0, 90.0, 0.0, 0.0, 0.0]


def _robot(host: str, port: int, move_timeout_s: float = 5.0) -> YaskawaHsesRobot:
    options = YaskawaHsesOptions(
        address=f"{host}:{port}",
        pulses_per_degree=PPD,
        move_timeout_s=move_timeout_s,
        request_timeout_s=0.05,
        retries=3,
        poll_s=0.002,
    )
    return YaskawaHsesRobot(host, port, options=options)


def _until(ok: Callable[[], bool], what: str, within_s: float = 5.0) -> None:
    deadline = time.monotonic() + within_s
    while not ok():
        assert time.monotonic() < deadline, what
        time.sleep(0.002)


def _pulse_error(q_deg: Sequence[float], target_deg: Sequence[float]) -> np.ndarray:
    return np.abs((np.asarray(q_deg, float) - np.asarray(target_deg, float)) * PPD)


@contextmanager
def _serving(fake: HsesFake, host: str) -> Iterator[tuple[str, int]]:
    """The fake serving on ``host``; at the end, every datagram it was sent had been
    well formed and known to it, and it is stopped in any case."""
    address = fake.start(host, 0)
    try:
        yield address
        assert fake.malformed == [] and fake.unknown == []
    finally:
        fake.stop()


def _one_line(e: pytest.ExceptionInfo[DeviceError], host: str, port: int) -> str:
    text = str(e.value)
    assert "\n" not in text
    assert text.startswith(f"yaskawa-robot at {host}:{port}: "), text
    return text


def test_connect_turns_the_servo_on_and_moves_land_within_half_a_pulse():
    fake = HsesFake(PPD, time_scale=0.2)
    with _serving(fake, "127.0.0.58") as (host, port):
        assert not fake.servo_on
        targets = ([10.5, -80.25, 85.0, 5.0, 30.0, 12.0], [-20.0, -60.0, 70.0, 0.0, 10.0, 0.0])
        with _robot(host, port) as r:
            assert fake.servo_on
            assert [q.u32() for q in fake.sent(0x83, 2)] == [1]
            assert _pulse_error(np.degrees(r.actual_joints()), HOME).max() <= 0.5
            for target, speed in zip(targets, (0.5, 0.25), strict=True):
                r.move_joints(np.radians(target), speed)
                assert _pulse_error(np.degrees(r.actual_joints()), target).max() <= 0.5
                assert _pulse_error(fake.q_deg(), target).max() <= 0.5
        assert [m.speed for m in fake.moves] == [5000, 2500]  # 0.01 %
        for move, target in zip(fake.moves, targets, strict=True):
            assert (move.robot, move.station, move.speed_class, move.tool) == (1, 0, 0, 0)
            assert np.abs(np.asarray(move.pulses[:6]) - np.multiply(target, PPD)).max() <= 0.5
            assert move.pulses[6:] == (0, 0) and not any(move.extra)
            assert move.refused == 0
        ids = [q.request_id for q in fake.requests]
        assert all(1 <= i <= 255 for i in ids)
        assert all(a != b for a, b in itertools.pairwise(ids))  # each its own id


def test_refusals_are_one_line():
    fake = HsesFake(PPD)
    with _serving(fake, "127.0.0.59") as (host, port):
        for switch, expected in (
            ("teach", "connect refused: the controller is in TEACH"),
            ("pendant_hold", "connect refused: held by the pendant's HOLD"),
            ("servo_locked", "servo on refused: status 0x1F, added status 0x3450"),
        ):
            setattr(fake, switch, True)
            with pytest.raises(DeviceError) as e:
                _robot(host, port).connect()
            assert expected in _one_line(e, host, port)
            setattr(fake, switch, False)
        fake.remote = False
        with pytest.raises(DeviceError) as e:
            _robot(host, port).connect()
        assert "connect refused: command remote is not set" in _one_line(e, host, port)
        fake.remote = True
        assert fake.moves == []
        with _robot(host, port) as r:
            fake.teach = True
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            assert "move refused: the controller is in TEACH" in _one_line(e, host, port)
            fake.teach = False
            fake.remote = False
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            assert "move refused: command remote is not set" in _one_line(e, host, port)
            fake.remote = True
            fake.refuse_moves = (0x1F, 0x2070)  # the servo dropped between look and move
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            text = _one_line(e, host, port)
            assert "move refused: status 0x1F, added status 0x2070 (servo off)" in text
            fake.refuse_moves = (0x01, 0)  # a status without an added status
            with pytest.raises(DeviceError) as e:
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            assert "move refused: status 0x01" in _one_line(e, host, port)
            fake.refuse_moves = None
            r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
        assert _pulse_error(fake.q_deg(), [1, -90, 90, 0, 0, 0]).max() <= 0.5


def test_an_alarm_mid_move_is_one_line_and_the_next_connection_resets_it():
    fake = HsesFake(PPD, time_scale=0.5)
    with _serving(fake, "127.0.0.58") as (host, port):
        # inside the model's limits (axis 1 ±155°), beyond the fake's (±120°)
        with _robot(host, port) as r, pytest.raises(DeviceError) as e:
            r.move_joints(np.radians([140.0, -90, 90, 0, 0, 0]), 0.5)
        text = _one_line(e, host, port)
        assert re.search(r"move failed: alarm 4601 \(PULSE LIMIT OVER S\) is active", text)
        alarm = fake.alarm
        assert alarm is not None and alarm.code == 4601
        assert not fake.servo_on
        assert abs(fake.q_deg()[0] - 120.0) <= 1 / PPD[0]  # stopped on the limit, mid-way
        assert fake.sent(0x70, 1)
        with _robot(host, port) as r:
            assert fake.alarm is None and fake.servo_on
            assert [q.u32() for q in fake.sent(0x82, 1)] == [1]
            r.move_joints(np.radians(HOME), 0.5)
            assert _pulse_error(np.degrees(r.actual_joints()), HOME).max() <= 0.5


def test_lost_repeated_and_stale_datagrams_are_survived():
    fake = HsesFake(
        PPD, time_scale=0.2, lose_every=7, lose_every_move=2, duplicate_every=5, stale_every=4
    )
    with _serving(fake, "127.0.0.59") as (host, port):
        targets = [[10.0 * i, -80.0, 85.0, 5.0, 30.0 - i, 12.0] for i in range(4)]
        with _robot(host, port) as r:
            for target in targets:
                r.move_joints(np.radians(target), 0.5)
                assert _pulse_error(np.degrees(r.actual_joints()), target).max() <= 0.5
                assert _pulse_error(fake.q_deg(), target).max() <= 0.5
            assert r.resent > 0 and r.dropped > 0
        assert fake.lost > 0 and fake.duplicated > 0 and fake.stale_sent > 0
        assert any(q.command == 0x8B and q.fate == "lost" for q in fake.requests)
        assert len([m for m in fake.moves if m.refused == 0]) == len(targets)


def test_a_late_running_bit_and_a_jittering_position():
    # the running bit comes on 0.3 s after a move is accepted: these moves are over by then
    fake = HsesFake(PPD, time_scale=0.2, motion_delay_s=0.05, running_delay_s=0.3, jitter_pulses=1)
    with _serving(fake, "127.0.0.58") as (host, port), _robot(host, port) as r:
        for target in ([30.0, -70.0, 60.0, 20.0, -30.0, 45.0], HOME):
            r.move_joints(np.radians(target), 0.5)
            assert _pulse_error(fake.q_deg(), target).max() <= 2.5  # not left behind
            # a reading of ±1 pulse around the target, rounded to a pulse
            assert _pulse_error(np.degrees(r.actual_joints()), target).max() <= 1.5
            _until(lambda: not fake.moving, "the fake's robot standing")
            assert _pulse_error(fake.q_deg(), target).max() <= 0.5


def test_stop_holds_and_the_next_move_releases_the_hold():
    fake = HsesFake(PPD, time_scale=0.2)
    with _serving(fake, "127.0.0.58") as (host, port), _robot(host, port) as r:
        r.move_joints(np.radians([5, -85, 95, 0, 0, 0]), 0.5)
        r.stop()
        assert fake.command_hold
        assert [q.u32() for q in fake.sent(0x83, 1)] == [1]
        r.move_joints(np.radians(HOME), 0.5)
        assert not fake.command_hold
        holds = fake.sent(0x83, 1)
        assert [q.u32() for q in holds] == [1, 2]
        assert holds[-1].at <= fake.sent(0x8B)[-1].at  # released before the move
        assert _pulse_error(np.degrees(r.actual_joints()), HOME).max() <= 0.5
