"""cellcal's FANUC RMI driver against a fake controller written apart from cellcal's twin,
from docs/robots.md and the RMI manual's packet list alone (tests/fakes/rmi_plain_fake.py),
over real sockets on 127.0.0.17 and .18: moves and the measured joints, consecutive
sequence ids, and the faults a cell meets. The fake sends integers as JSON floats, keys
in another order, unknown fields, a status split across segments and noisy joints; the
twin does none of these."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.drivers.fanuc_rmi import FanucRmiOptions, FanucRmiRobot
from cellcal.errors import DeviceError
from tests.fakes.rmi_plain_fake import RmiPlainFake

pytestmark = pytest.mark.timeout(60)


def _robot(host: str, port: int, **options: object) -> FanucRmiRobot:
    o = FanucRmiOptions(address=f"{host}:{port}", move_timeout_s=5.0, **options)  # type: ignore[arg-type]
    return FanucRmiRobot(host, port, options=o)


def test_the_driver_moves_and_reads_through_another_fake():
    fake = RmiPlainFake()
    host, port = fake.start("127.0.0.17", 0)
    try:
        with _robot(host, port) as r:
            assert r.describe().firmware == "RMI 3.9"
            np.testing.assert_allclose(np.degrees(r.actual_joints()), fake.joints, atol=1e-3)
            for target in ([10.5, -20.25, 35.0, 5.0, -10.0, 12.0], [-20, -40, 50, 0, 10, 0]):
                r.move_joints(np.radians(target), 0.5)
                np.testing.assert_allclose(np.degrees(r.actual_joints()), target, atol=1e-3)
                np.testing.assert_allclose(fake.joints, target, atol=1e-9)
            with pytest.raises(DeviceError, match="ErrorID 2556954"):
                _robot(host, port, request_timeout_s=0.3).connect()
            r.stop()  # FRC_Abort: the next move initialises again
            r.move_joints(np.radians([0, -30, 40, 0, -20, 0]), 0.5)
        moves = [p["SequenceID"] for p in fake.received if "Instruction" in p]
        assert moves == [1, 2, 1]
        names = [p.get("Command") for p in fake.received]
        assert names.count("FRC_Initialize") == 2 and "FRC_Abort" in names
    finally:
        fake.stop()


def test_faults_of_the_other_fake_are_one_line():
    fake = RmiPlainFake(idle_s=0.3)
    host, port = fake.start("127.0.0.18", 0)
    try:
        fake.tp_enabled = True
        with pytest.raises(DeviceError, match="connect refused: the teach pendant is enabled"):
            _robot(host, port).connect()
        fake.tp_enabled = False
        with _robot(host, port) as r:
            with pytest.raises(DeviceError) as err:
                r.move_joints(np.radians([170, -30, 40, 0, -20, 0]), 0.5)
            line = str(err.value)
            assert line.startswith(f"fanuc-robot at {host}:{port}: system fault during the move")
            assert "MOTN-017 Limit error (G:1^A:1) (fake)" in line and "\n" not in line
            deadline = time.monotonic() + 10  # the fake ends the silent session
            while fake.session_up.is_set():
                assert time.monotonic() < deadline
                time.sleep(0.02)
            goal = [5.0, -25.0, 45.0, 0.0, -20.0, 0.0]
            r.move_joints(np.radians(goal), 0.5)  # a new session: reset, initialise
            np.testing.assert_allclose(np.degrees(r.actual_joints()), goal, atol=1e-3)
    finally:
        fake.stop()
