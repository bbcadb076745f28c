"""The UR twin refuses joint targets outside a UR e-Series' joint ranges (±360° on every
joint), as the controller does: a protective stop, the robot does not move, the move
fails (issue 29, item 4). Driven by the unmodified ur_rtde and by cellcal's driver."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.drivers.ur import URRobot
from cellcal.errors import DeviceError
from tests.mocks.test_ur_twin_wire import dashboard
from tests.mocks.ur_clients import Q0, Q1, clients, ur_twin, wait_for

pytestmark = pytest.mark.twin

pytest.importorskip("rtde_control")  # UR's own client (make fetches it): skipped without it


@pytest.mark.timeout(60, method="thread")
@pytest.mark.parametrize(("joint", "deg"), [(5, 720.0), (0, -361.0)])
def test_movej_beyond_a_joint_range_is_a_protective_stop(joint, deg):
    host = "127.0.0.150" if joint == 5 else "127.0.0.151"
    with ur_twin(host) as sim, clients(host) as ur:
        target = Q0.copy()
        target[joint] = np.radians(deg)
        assert not ur.c.moveJ(target.tolist(), 1.0, 1.4)
        np.testing.assert_allclose(sim.q, Q0, atol=1e-12)  # it never moved
        wait_for(lambda: ur.r.isProtectiveStopped(), "the protective stop")
        assert dashboard(host, ["safetystatus"])[1] == "Safetystatus: PROTECTIVE_STOP"
        assert dashboard(host, ["unlock protective stop"])[1] == "Protective stop releasing"
        wait_for(lambda: not ur.r.isProtectiveStopped(), "the protective stop to clear")
        # Within the ranges it moves again (the control link may lag the unlock a cycle).
        wait_for(lambda: ur.c.moveJ(Q1.tolist(), 3.0, 10.0), "a move after the unlock")
        np.testing.assert_allclose(sim.q, Q1, atol=1e-12)


@pytest.mark.timeout(60, method="thread")
def test_the_driver_reports_the_refusal_in_one_line():
    host = "127.0.0.152"
    with ur_twin(host) as sim:
        robot = URRobot(host, name="arm", timeout_s=20)
        robot.connect()
        try:
            target = Q0.copy()
            target[3] = np.radians(540.0)
            with pytest.raises(DeviceError) as info:
                robot.move_joints(target, 0.5)
            assert "\n" not in str(info.value) and "protective stop" in str(info.value)
            np.testing.assert_allclose(sim.q, Q0, atol=1e-12)
        finally:
            robot.close()
