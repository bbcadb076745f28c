"""The one factory that turns a configuration into devices.

It is the only place allowed to build simulated devices (mock mode). In mock mode the
laser trackers are reached through the real line-protocol driver over TCP, talking to a
protocol-level mock tracker (a thread on 127.0.0.5, its own port) that serves the
simulated cell; the robot and the photogrammetry rig are still in-process simulated
devices behind the driver Protocols. Drivers for real robots arrive with their own
issue; until then a configuration without --mock is refused here with a clear line.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from cellcal.calib.robot_model import RobotModel
from cellcal.clock import Clock
from cellcal.config import CellConfig
from cellcal.daemon.engine import SensorSetting
from cellcal.drivers.base import PositionSensor, Robot
from cellcal.drivers.safety import GuardedRobot
from cellcal.drivers.tracker import LineTracker
from cellcal.errors import DeviceError


@dataclass(frozen=True)
class Devices:
    robot: Robot
    sensors: tuple[SensorSetting, ...]
    simulated_cell: object | None  # the mock cell's truth, for tests and reports
    servers: tuple[Closeable, ...] = ()  # protocol-level mock servers (mock mode)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.robot.stop()
        self.robot.close()
        for s in self.sensors:
            s.sensor.close()
        for srv in self.servers:
            srv.stop()


class Closeable(Protocol):
    def stop(self) -> None: ...


#: Loopback address of the mock laser trackers (each on its own ephemeral port).
MOCK_TRACKER_HOST = "127.0.0.5"


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
    from cellcal.mocks.tracker_server import MockTracker

    cell = SimulatedCell(config, nominal, seed, noise_stream)
    robot = _guarded(SimulatedRobot(cell, clock), config, nominal)
    sensors: list[SensorSetting] = []
    servers: list[Closeable] = []
    try:
        for s in config.sensor:
            if s.kind == "laser-tracker":
                # The real driver, over TCP, against a protocol-level mock of this tracker.
                server = MockTracker(
                    cell.target(s.name), time_scale=getattr(clock, "time_scale", 0.0)
                )
                servers.append(server)
                host, port = server.start_tcp(MOCK_TRACKER_HOST, 0)
                sensor: PositionSensor = LineTracker(
                    s.name, f"socket://{host}:{port}", clock=clock, timeout=10.0
                )
            else:
                sensor = SimulatedSensor(cell, clock, s.name)
            sensor.connect()
            sensors.append(SensorSetting(sensor, s.rate_hz))
        robot.connect()
    except BaseException:
        for srv in servers:
            srv.stop()
        raise
    return Devices(robot, tuple(sensors), cell, tuple(servers))


def _guarded(robot: Robot, config: CellConfig, nominal: RobotModel) -> GuardedRobot:
    """Every robot, simulated or real, behind the safety gate."""
    c = config.campaign
    return GuardedRobot(
        robot,
        nominal,
        np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64),
        np.asarray(c.workspace_min_mm, dtype=np.float64),
        np.asarray(c.workspace_max_mm, dtype=np.float64),
        config.robot.max_speed,
    )
