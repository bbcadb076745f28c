"""One contract every robot family of the registry passes — built by the device factory
from a cell configuration, in mock mode its real driver against its twin — behind the
safety gate, as the campaign uses them. A family added to the table is picked up here."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.config import with_robot
from cellcal.drivers.safety import SafetyError
from cellcal.errors import DeviceError
from cellcal.families import families
from cellcal.mocks.modbus.server import ModbusRobotFaults
from tests.drivers.families import cell_for, mock_devices

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(90)]

ROBOTS = families("robot")


@pytest.mark.parametrize("family", ROBOTS, ids=[f.tag for f in ROBOTS])
def test_contract(family):
    config = cell_for(family)
    home = np.radians(config.robot.home_deg)
    with mock_devices(config) as devices:
        robot, cell = devices.robot, devices.simulated_cell
        assert type(robot.robot).__name__ == family.device.rpartition(":")[2]
        np.testing.assert_allclose(robot.actual_joints(), home, atol=1e-6)
        target = home + np.radians([5.0, -4.0, 6.0, 3.0, -5.0, 10.0])
        robot.move_joints(target, 0.25)
        np.testing.assert_allclose(robot.actual_joints(), target, atol=1e-4)
        # The simulated cell follows the controller: sensors see where it really is.
        np.testing.assert_allclose(cell.q, target, atol=1e-4)
        robot.move_joints(home, 0.5)
        np.testing.assert_allclose(robot.actual_joints(), home, atol=1e-4)
        # The gate refuses before anything is sent.
        lo, _ = cell.model.limits
        bad = home.copy()
        bad[0] = lo[0] - 0.1
        with pytest.raises(SafetyError, match="joint 1"):
            robot.move_joints(bad, 0.25)
        with pytest.raises(SafetyError, match="speed"):
            robot.move_joints(home, 0.9)
        np.testing.assert_allclose(robot.actual_joints(), home, atol=1e-4)
        robot.stop()


def _family(driver):
    return next(f for f in ROBOTS if f.driver == driver)


def test_modbus_faults_end_the_move_with_one_clear_error():
    with mock_devices(cell_for(_family("modbus"))) as devices:
        devices.servers[0].server.faults = ModbusRobotFaults(estop=True)
        with pytest.raises(DeviceError, match="e-stop"):
            devices.robot.move_joints(devices.robot.actual_joints() + 0.05, 0.25)


def test_modbus_map_with_holes_from_the_configuration():
    """[robot.map] with holes (heartbeat 4 and status 7 beside error code 2 and ack 3;
    the blocks moved apart): the factory's driver connects to the twin, which has these
    registers and no other, and moves; no status read crosses a hole."""
    holed = {"heartbeat": 4, "status": 7, "actual_joints": 40, "actual_pose": 70,
             "target_joints": 300, "speed": 400, "command": 500, "sequence": 501}  # fmt: skip
    config = with_robot(cell_for(_family("modbus")), map=holed)
    home = np.radians(config.robot.home_deg)
    with mock_devices(config) as devices:
        robot, twin = devices.robot, devices.servers[0].server
        for step in ([5.0, -4.0, 6.0, 3.0, -5.0, 10.0], [-3.0, 2.0, -4.0, 0.0, 6.0, -8.0]):
            target = home + np.radians(step)
            robot.move_joints(target, 0.25)
            np.testing.assert_allclose(robot.actual_joints(), target, atol=1e-4)
        robot.move_joints(home, 0.5)
        np.testing.assert_allclose(devices.simulated_cell.q, home, atol=1e-4)
        reads = {(r.address, r.count) for r in twin.requests if r.values is None}
    assert reads == {(2, 3), (7, 1), (40, 12)}


def test_ur_protective_stop_is_an_error():
    with mock_devices(cell_for(_family("ur"))) as devices:
        devices.servers[0].server.inject_protective_stop()
        with pytest.raises(DeviceError, match="protective"):
            devices.robot.move_joints(devices.robot.actual_joints() + 0.05, 0.25)
