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
from typing import TYPE_CHECKING, Protocol

import numpy as np

from cellcal.calib.robot_model import RobotModel
from cellcal.clock import Clock
from cellcal.config import CellConfig
from cellcal.daemon.engine import SensorSetting
from cellcal.drivers.base import PositionSensor, Robot
from cellcal.drivers.safety import GuardedRobot
from cellcal.drivers.tracker import LineTracker
from cellcal.errors import DeviceError

if TYPE_CHECKING:
    from cellcal.drivers.modbus_robot import ModbusMap
    from cellcal.mocks.simulated_cell import SimulatedCell


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


#: Loopback addresses of the protocol-level mocks: trackers and Modbus robots take an
#: ephemeral port each; a simulated UR needs the fixed ports 30004/29999/30003, so each
#: takes the first free address of its range.
MOCK_TRACKER_HOST = "127.0.0.5"
MOCK_MODBUS_HOST = "127.0.0.3"
MOCK_UR_HOSTS = tuple(f"127.0.0.{k}" for k in range(100, 140))


def _host_port(address: str, default_port: int) -> tuple[str, int]:
    host, sep, port = address.rpartition(":")
    if sep and port.isdigit():
        return host, int(port)
    return address, default_port


def _modbus_map(config: CellConfig) -> ModbusMap:
    from cellcal.drivers.modbus_robot import ModbusMap

    m = config.robot.modbus
    return ModbusMap(
        heartbeat=m.heartbeat,
        status=m.status,
        error_code=m.error,
        ack=m.ack,
        actual_joints=m.actual_joints,
        actual_pose=m.actual_pose,
        target_joints=m.target_joints,
        target_pose=m.target_pose,
        speed=m.speed,
        command=m.command,
        sequence=m.sequence,
        word_order=m.word_order,
        device_id=m.device_id,
    )


def _real_devices(config: CellConfig, nominal: RobotModel, clock: Clock) -> Devices:
    r = config.robot
    if r.driver == "simulated":
        raise DeviceError('robot.driver = "simulated" needs --mock')
    if not r.address:
        raise DeviceError(f"robot.address is empty: where is the {r.driver} controller?")
    robot: Robot
    if r.driver == "modbus":
        from cellcal.drivers.modbus_robot import ModbusRobot

        host, port = _host_port(r.address, r.modbus.port)
        robot = ModbusRobot(host, port, map=_modbus_map(config), timeout_s=r.modbus.timeout_s)
    elif r.driver == "ur":
        from cellcal.drivers.ur import URRobot

        robot = URRobot(r.address, timeout_s=r.settle_timeout_s)
    else:
        raise DeviceError(f"robot.driver {r.driver!r}: no such driver")
    sensors: list[SensorSetting] = []
    for s in config.sensor:
        if s.kind == "laser-tracker" and s.driver == "line-protocol":
            if not s.url:
                raise DeviceError(f"sensor {s.name}: url is empty")
            sensors.append(SensorSetting(LineTracker(s.name, s.url, clock=clock), s.rate_hz))
        else:
            raise DeviceError(
                f"sensor {s.name}: no driver for a {s.kind} with driver = {s.driver!r} in this "
                'version (a laser tracker takes driver = "line-protocol"); run with --mock'
            )
    guarded = _guarded(robot, config, nominal)
    opened: list[SensorSetting] = []
    try:
        for st in sensors:
            st.sensor.connect()
            opened.append(st)
        guarded.connect()
    except BaseException:
        for st in opened:
            with contextlib.suppress(Exception):
                st.sensor.close()
        raise
    return Devices(guarded, tuple(sensors), None)


def build_devices(
    config: CellConfig,
    nominal: RobotModel,
    clock: Clock,
    *,
    mock: bool,
    seed: int | None,
    noise_stream: int = 0,
) -> Devices:
    """Connect the configured devices, or in mock mode the simulated cell's."""
    if not mock:
        return _real_devices(config, nominal, clock)
    from cellcal.mocks.simulated_cell import SimulatedCell
    from cellcal.mocks.simulated_devices import SimulatedSensor
    from cellcal.mocks.tracker_server import MockTracker

    cell = SimulatedCell(config, nominal, seed, noise_stream)
    time_scale = float(getattr(clock, "time_scale", 0.0))
    sensors: list[SensorSetting] = []
    servers: list[Closeable] = []
    try:
        robot = _guarded(_mock_robot(config, cell, clock, time_scale, servers), config, nominal)
        for s in config.sensor:
            if s.kind == "laser-tracker":
                # The real driver, over TCP, against a protocol-level mock of this tracker.
                server = MockTracker(cell.target(s.name), time_scale=time_scale)
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


def _mock_robot(
    config: CellConfig,
    cell: SimulatedCell,
    clock: Clock,
    time_scale: float,
    servers: list[Closeable],
) -> Robot:
    """The configured robot driver, against a protocol-level mock following the cell; or
    the in-process simulated robot for driver = "simulated"."""
    import math

    from cellcal.mocks.simulated_devices import SimulatedRobot

    r = config.robot
    if r.driver == "simulated":
        return SimulatedRobot(cell, clock)
    lo, hi = cell.model.limits
    limits = [(math.degrees(a), math.degrees(b)) for a, b in zip(lo, hi, strict=True)]
    if r.driver == "modbus":
        from cellcal.drivers.modbus_robot import ModbusRobot
        from cellcal.mocks.modbus_robot_server import ModbusRobotSimulator

        sim = ModbusRobotSimulator(
            q0_deg=list(r.home_deg),
            limits_deg=limits,
            joint_speed_deg_s=config.simulation.joint_speed_deg_s,
            time_scale=time_scale,
            word_order=r.modbus.word_order,
            device_id=r.modbus.device_id,
            on_move=cell.set_q,
            pose_fn=cell.flange_pose,
        )
        servers.append(sim)
        host, port = sim.start(MOCK_MODBUS_HOST, 0)
        # On loopback the status can be polled faster than a PLC cycle.
        return ModbusRobot(
            host,
            port,
            map=_modbus_map(config),
            timeout_s=r.modbus.timeout_s,
            poll_s=0.002,
        )
    from cellcal.drivers.ur import URRobot
    from cellcal.mocks.ur_server import URSimulator

    kin = cell.ur_kinematics()
    last: Exception | None = None
    for host in MOCK_UR_HOSTS:
        ur = URSimulator(kin, q0=np.radians(r.home_deg), time_scale=time_scale, on_move=cell.set_q)
        try:
            ur.start(host)
        except OSError as exc:  # another simulated UR holds this address's fixed ports
            last = exc
            continue
        servers.append(ur)
        return URRobot(host, timeout_s=r.settle_timeout_s)
    raise DeviceError(f"no free loopback address for a simulated UR ({last})")


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
