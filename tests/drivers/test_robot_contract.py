"""One contract every robot backend passes — the in-process simulated robot, the Modbus
driver against the pymodbus mock, the UR driver (ur_rtde) against the UR simulator —
each behind the safety gate, as the campaign uses them."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from cellcal.clock import SimulatedClock
from cellcal.commands.run import bundled_mock_cell
from cellcal.config import config_from_dict
from cellcal.daemon.devices import _guarded
from cellcal.drivers.modbus_robot import ModbusRobot
from cellcal.drivers.safety import SafetyError
from cellcal.drivers.ur import URRobot
from cellcal.errors import DeviceError
from cellcal.mocks.modbus_robot_server import ModbusRobotFaults, ModbusRobotSimulator
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.simulated_devices import SimulatedRobot
from cellcal.mocks.ur_server import URSimulator
from cellcal.modelfiles import load_model

pytestmark = pytest.mark.timeout(90)

UR_CONFIG = {
    "robot": {
        "model": "ur10e",
        "driver": "ur",
        "home_deg": [0.0, -100.0, 100.0, -90.0, -90.0, 0.0],
    },
    "sensor": [{"name": "tracker", "kind": "laser-tracker", "reference": True}],
    "campaign": {"workspace_min_mm": [-1400, -1400, -200], "workspace_max_mm": [1400, 1400, 1400]},
}


@contextlib.contextmanager
def backend(kind: str, host_index: int = 0):
    """(robot behind the gate, the simulated cell it drives, the server's fault switch)."""
    config = config_from_dict(UR_CONFIG) if kind == "ur" else bundled_mock_cell()[0]
    nominal = load_model(config.robot.model).model
    cell = SimulatedCell(config, nominal, 5)
    home = np.radians(config.robot.home_deg)
    server = None
    if kind == "simulated":
        robot = SimulatedRobot(cell, SimulatedClock())
    elif kind == "modbus":
        lo, hi = nominal.limits
        server = ModbusRobotSimulator(
            q0_deg=np.degrees(home),
            limits_deg=list(zip(np.degrees(lo), np.degrees(hi), strict=True)),
            on_move=cell.set_q,
            pose_fn=cell.flange_pose,
        )
        host, port = server.start("127.0.0.3", 0)
        robot = ModbusRobot(host, port, timeout_s=20.0)
    else:
        server = URSimulator(cell.ur_kinematics(), q0=home, on_move=cell.set_q)
        host = f"127.0.0.{150 + host_index}"
        server.start(host)
        robot = URRobot(host, timeout_s=30.0)
    gated = _guarded(robot, config, nominal)
    try:
        gated.connect()
        yield gated, cell, server, home
    finally:
        with contextlib.suppress(Exception):
            gated.close()
        if server is not None:
            server.stop()


@pytest.mark.parametrize("kind", ["simulated", "modbus", "ur"])
def test_contract(kind):
    with backend(kind, 0) as (robot, cell, _, home):
        np.testing.assert_allclose(robot.actual_joints(), home, atol=1e-6)
        target = home + np.radians([5.0, -4.0, 6.0, 3.0, -5.0, 10.0])
        robot.move_joints(target, 0.25)
        np.testing.assert_allclose(robot.actual_joints(), target, atol=1e-4)
        # The simulated cell follows the controller: instruments see where it really is.
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


def test_modbus_faults_end_the_move_with_one_clear_error():
    with backend("modbus") as (robot, _, server, home):
        server.faults = ModbusRobotFaults(estop=True)
        with pytest.raises(DeviceError, match="e-stop"):
            robot.move_joints(home + 0.05, 0.25)


def test_ur_protective_stop_is_an_error():
    with backend("ur", 1) as (robot, _, server, home):
        server.inject_protective_stop()
        with pytest.raises(DeviceError, match="protective"):
            robot.move_joints(home + 0.05, 0.25)
