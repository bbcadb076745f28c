"""cellcal's Yaskawa HSES driver against a fake controller written apart from cellcal's
twin, from docs/robots.md and fs100's layouts alone (tests/fakes/hses_plain_fake.py),
over real UDP sockets on 127.0.0.58 and .59: the servo turned on, moves landing at their
targets, the records sent, lost, doubled and stale answers survived, a hold released, and
the faults a cell meets. The fake's running bit lags the move and its position jitters
by a pulse; the twin does neither."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from cellcal.drivers.yaskawa_hses import YaskawaHsesOptions, YaskawaHsesRobot
from cellcal.errors import DeviceError
from tests.fakes.hses_plain_fake import HsesPlainFake

pytestmark = pytest.mark.timeout(60)

PPD = [1300.5, 1210.0, 1150.25, 700.0, 690.75, 400.0]


def _robot(host: str, port: int, **options: object) -> YaskawaHsesRobot:
    o = YaskawaHsesOptions(
        address=f"{host}:{port}", pulses_per_degree=PPD, move_timeout_s=5.0,
        request_timeout_s=0.2, poll_s=0.005, **options,  # type: ignore[arg-type]
    )  # fmt: skip
    return YaskawaHsesRobot(host, port, options=o)


def _read_what_is_in_flight(r: YaskawaHsesRobot, fake: HsesPlainFake) -> None:
    """The last doubled answers may still be on their way when a move returns (the fake
    sends each from its own thread): with the faults off, read the position until the
    driver has dropped every extra answer the fake sent, for at most 2 s."""
    fake.lose_every = fake.double_every = fake.stale_every = 0
    deadline = time.monotonic() + 2.0
    while r.dropped < fake.doubled + fake.stale and time.monotonic() < deadline:
        r.actual_joints()


def test_the_driver_moves_through_another_fake_and_survives_its_datagrams():
    fake = HsesPlainFake(PPD)
    fake.lose_every, fake.double_every, fake.stale_every = 5, 4, 7
    host, port = fake.start("127.0.0.58", 0)
    try:
        with _robot(host, port, retries=4) as r:
            assert fake.servo
            for target in ([10.0, -20.5, 33.25, 5.0, -12.0, 40.0], [-15.0, -35, 45, 0, 10, -5]):
                r.move_joints(np.radians(target), 0.5)
                half_pulse = 0.5 / np.array(PPD) + 1.0 / np.array(PPD)  # and ±1 of jitter
                assert (np.abs(np.degrees(r.actual_joints()) - target) <= half_pulse).all()
            assert r.resent >= fake.lost > 0 and fake.doubled + fake.stale > 0
            _read_what_is_in_flight(r, fake)
            assert r.dropped >= fake.doubled + fake.stale
            fake.lose_every, fake.double_every, fake.stale_every = 5, 4, 7
            r.stop()
            assert fake.hold
            r.move_joints(np.radians([0, -30, 40, 0, -20, 0]), 0.5)  # releases the hold
            assert not fake.hold
        moves = [d for c, _, _, d in fake.requests if c == 0x8B]
        first = struct.unpack("<22i", moves[0])
        assert first[:4] == (1, 0, 0, 5000)
        assert first[4:10] == tuple(
            round(d * p) for d, p in zip([10.0, -20.5, 33.25, 5.0, -12.0, 40.0], PPD, strict=True)
        )
    finally:
        fake.stop()


def test_faults_of_the_other_fake_are_one_line():
    fake = HsesPlainFake(PPD)
    host, port = fake.start("127.0.0.59", 0)
    try:
        fake.teach = True
        with pytest.raises(DeviceError, match="connect refused: the controller is in TEACH"):
            _robot(host, port).connect()
        fake.teach, fake.remote = False, False
        with pytest.raises(DeviceError, match="connect refused: command remote is not set"):
            _robot(host, port).connect()
        fake.remote = True
        with _robot(host, port) as r:
            with pytest.raises(DeviceError) as err:
                r.move_joints(np.radians([170, -30, 40, 0, -20, 0]), 0.5)
            line = str(err.value)
            assert line.startswith(f"yaskawa-robot at {host}:{port}: move failed: alarm 4321")
            assert "OVERRUN AXIS S (fake)" in line and "\n" not in line
        with _robot(host, port) as again:  # connect resets the alarm
            again.move_joints(np.radians([3, -28, 42, 0, -18, 2]), 0.5)
            assert fake.alarm == 0
    finally:
        fake.stop()
