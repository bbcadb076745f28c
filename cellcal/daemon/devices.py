"""The one factory that turns a configuration into devices.

It is the only place allowed to build simulated devices (mock mode). Real drivers for
the tracker line protocol, Universal Robots and Modbus robots arrive with their own
issues; until then a configuration that names them is refused here with a clear line.
"""

from __future__ import annotations

from dataclasses import dataclass

from cellcal.calib.robot_model import RobotModel
from cellcal.clock import Clock
from cellcal.config import CellConfig
from cellcal.daemon.engine import SensorSetting
from cellcal.drivers.base import Robot
from cellcal.errors import DeviceError


@dataclass(frozen=True)
class Devices:
    robot: Robot
    sensors: tuple[SensorSetting, ...]
    simulated_cell: object | None  # the mock cell's truth, for tests and reports


def build_devices(
    config: CellConfig,
    nominal: RobotModel,
    clock: Clock,
    *,
    mock: bool,
    seed: int | None,
    noise_stream: int = 0,
) -> Devices:
    """Connect the configured devices (or their simulated twins in mock mode)."""
    if not mock:
        raise DeviceError(
            'this version drives only the simulated cell (driver = "simulated"); run with --mock'
        )
    from cellcal.mocks.simulated_cell import SimulatedCell
    from cellcal.mocks.simulated_devices import SimulatedRobot, SimulatedSensor

    cell = SimulatedCell(config, nominal, seed, noise_stream)
    robot = SimulatedRobot(cell, clock)
    sensors = tuple(
        SensorSetting(SimulatedSensor(cell, clock, s.name), s.rate_hz) for s in config.sensor
    )
    robot.connect()
    for s in sensors:
        s.sensor.connect()
    return Devices(robot, sensors, cell)
