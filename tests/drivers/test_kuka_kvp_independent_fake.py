"""cellcal's KUKA driver against a KUKAVARPROXY fake written by another hand from the
published protocol facts alone (tests/fakes/kvp_fake.py, not from cellcal's twin), over
real sockets on 127.0.0.177–.178: the campaign's moves, reads and faults."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.drivers.kuka_kvp import KukaKvpOptions, KukaKvpRobot
from cellcal.errors import DeviceError
from tests.fakes.kvp_fake import KvpFake

pytestmark = pytest.mark.timeout(60)


def _robot(host: str, port: int) -> KukaKvpRobot:
    options = KukaKvpOptions(address=f"{host}:{port}", move_timeout_s=3.0, poll_s=0.002)
    return KukaKvpRobot(host, port, options=options)


def test_the_driver_moves_and_reads_through_another_fake():
    fake = KvpFake(time_scale=0.01)
    host, port = fake.start("127.0.0.177", 0)
    try:
        with _robot(host, port) as r:
            np.testing.assert_allclose(
                np.degrees(r.actual_joints()), [0, -90, 90, 0, 0, 0], atol=1e-3
            )
            for target in (
                [10.5, -80.25, 85.0, 5.0, 30.0, 12.0],
                [-20.0, -60.0, 70.0, 0.0, 10.0, 0.0],
            ):
                r.move_joints(np.radians(target), 0.5)
                # the fake's encoders differ from the target by up to 0.0005°: the driver
                # returns the measured joints, not the target it sent
                np.testing.assert_allclose(np.degrees(r.actual_joints()), target, atol=1e-3)
                np.testing.assert_allclose(fake.q_deg(), target, atol=1e-3)
        names = [name.upper() for _, name, _ in fake.requests]
        assert "$AXIS_ACT_MEAS" in names and names.count("CC_SEQ") >= 2
    finally:
        fake.stop()


def test_faults_of_the_other_fake_are_one_line():
    fake = KvpFake()
    host, port = fake.start("127.0.0.178", 0)
    try:
        fake.mode = "#T1"
        with pytest.raises(DeviceError, match="connect refused: controller in T1"):
            _robot(host, port).connect()
        fake.mode = "#EX"
        with _robot(host, port) as r:
            fake.drives_on = False
            with pytest.raises(DeviceError, match=r"move refused: drives off"):
                r.move_joints(np.radians([1, -90, 90, 0, 0, 0]), 0.3)
            fake.drives_on = True
            fake.ack_enabled = False
            with pytest.raises(DeviceError, match=r"move not done after 3 s") as e:
                r.move_joints(np.radians([2, -90, 90, 0, 0, 0]), 0.3)
            assert "\n" not in str(e.value)
            fake.ack_enabled = True
            # beyond A3's limit: the fake raises a stop message, the driver names it
            with pytest.raises(DeviceError, match=r"stop message is active"):
                r.move_joints(np.radians([0, -90, 170, 0, 0, 0]), 0.3)
    finally:
        fake.stop()
