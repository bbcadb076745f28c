"""cellcal's EthernetKRL driver against a fake controller written by another hand from
docs/robots.md and the exported CellCalEki program alone (tests/fakes/eki_fake.py, not
from cellcal's twin), over real sockets on 127.0.0.195–.196: moves, the measured joints,
and the faults a cell meets. The fake writes its flags TRUE/FALSE, its numbers %.9g and
ends each telegram with CR LF; the twin does none of these."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.drivers.kuka_eki import KukaEkiOptions, KukaEkiRobot
from cellcal.errors import DeviceError
from tests.fakes.eki_fake import EkiFake

pytestmark = pytest.mark.timeout(60)


def _robot(host: str, port: int) -> KukaEkiRobot:
    options = KukaEkiOptions(address=f"{host}:{port}", move_timeout_s=3.0, poll_s=0.002)
    return KukaEkiRobot(host, port, options=options)


def test_the_driver_moves_and_reads_through_another_fake():
    fake = EkiFake(time_scale=0.01, cycle_s=0.01)
    host, port = fake.start("127.0.0.195", 0)
    try:
        with _robot(host, port) as r:
            np.testing.assert_allclose(
                np.degrees(r.actual_joints()), [0, -90, 90, 0, 0, 0], atol=1e-3
            )
            for target in ([10.5, -80.25, 85.0, 5.0, 30.0, 12.0], [-20, -60, 70, 0, 10, 0]):
                r.move_joints(np.radians(target), 0.5)
                np.testing.assert_allclose(np.degrees(r.actual_joints()), target, atol=1e-3)
                np.testing.assert_allclose(fake.q_deg(), target, atol=1e-6)
            with pytest.raises(DeviceError, match="closed the connection at once"):
                _robot(host, port).connect()
            assert fake.refused == 1
        assert sum("<Cmd " in c for c in fake.commands) == 2
    finally:
        fake.stop()


def test_faults_of_the_other_fake_are_one_line():
    fake = EkiFake(cycle_s=0.01)
    host, port = fake.start("127.0.0.196", 0)
    try:
        fake.mode = "#T1"
        with pytest.raises(DeviceError, match="connect refused: controller in T1"):
            _robot(host, port).connect()
        deadline = time.monotonic() + 5  # the channel is free once the fake saw the close
        while fake.busy:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        fake.mode = "#AUT"
        with _robot(host, port) as r:
            fake.guard_stop = True
            with pytest.raises(DeviceError, match="move refused: guard stop"):
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            fake.guard_stop = False
            fake.hang = True
            with pytest.raises(DeviceError, match=r"move not done after 3 s") as e:
                r.move_joints(np.radians([2, -90, 90, 0, 0, 0]), 0.3)
            assert "\n" not in str(e.value)
            deadline = time.monotonic() + 5  # the stop the driver sent on its way out
            while not any("<Stop " in c for c in fake.commands):
                assert time.monotonic() < deadline, fake.commands
                time.sleep(0.005)
            fake.hang = False
            with pytest.raises(DeviceError, match="stop message is active"):
                r.move_joints(np.radians([0, -90, 170, 0, 0, 0]), 0.3)
    finally:
        fake.stop()
