"""cellcal's ABB driver against an RWS 1.0 controller fake written by another hand from
public Robot Web Services facts alone (tests/fakes/rws_fake.py, not from cellcal's twin;
http.server, 32-bit RAPID nums, noisy measured joints, the request's uri checked in the
digest), over real sockets on 127.0.0.197–.198."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.drivers.abb_rws import AbbRwsOptions, AbbRwsRobot
from cellcal.errors import DeviceError
from tests.fakes.rws_fake import RwsFake

pytest.importorskip("httpx")
pytestmark = pytest.mark.timeout(60)


def _robot(address: str) -> AbbRwsRobot:
    return AbbRwsRobot(AbbRwsOptions(address=address, move_timeout_s=3.0, poll_s=0.002))


def test_the_driver_moves_and_reads_through_another_fake():
    fake = RwsFake(time_scale=0.01)
    host, port = fake.start("127.0.0.197", 0)
    try:
        with _robot(f"http://{host}:{port}") as r:
            assert r.describe().model == "IRB 1200"
            np.testing.assert_allclose(
                np.degrees(r.actual_joints()), [0, 0, 0, 0, 30, 0], atol=1e-3
            )
            for target in (
                [10.5, -20.25, 15.0, 5.0, 30.0, 12.0],
                [-20.0, 10.0, -30.0, 0.0, 45.0, 0.0],
            ):
                r.move_joints(np.radians(target), 0.5)
                np.testing.assert_allclose(np.degrees(r.actual_joints()), target, atol=1e-3)
                np.testing.assert_allclose(fake.q_deg(), target, atol=1e-4)
        assert sum(m == "POST" and "cc_seq" in p for m, p in fake.requests) == 2
    finally:
        fake.stop()


def test_faults_of_the_other_fake_are_one_line():
    fake = RwsFake()
    host, port = fake.start("127.0.0.198", 0)
    address = f"http://{host}:{port}"
    try:
        fake.opmode = "MANR"
        with pytest.raises(DeviceError, match="connect refused: controller in MANR"):
            _robot(address).connect()
        fake.opmode = "AUTO"
        with _robot(address) as r:
            fake.ctrlstate = "guardstop"
            with pytest.raises(DeviceError, match=r"motors are not on \(ctrlstate guardstop\)"):
                r.move_joints(np.radians([1, 0, 0, 0, 30, 0]), 0.3)
            fake.ctrlstate = "motoron"
            fake.mastership_held = True
            with pytest.raises(DeviceError, match="HTTP 403: RAPID mastership is held by another"):
                r.move_joints(np.radians([2, 0, 0, 0, 30, 0]), 0.3)
            fake.mastership_held = False
            # beyond the IRB 1200's axis 3: RAPID stops
            with pytest.raises(DeviceError, match=r"RAPID is not running \(execution stopped\)"):
                r.move_joints(np.radians([0, 0, -115, 0, 30, 0]), 0.3)
    finally:
        fake.stop()
