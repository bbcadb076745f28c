"""The one factory that turns a configuration into devices: a loop over the configured
devices, each built by its family (``cellcal/families.py``).

Real mode: each device's driver, from its options, at its configured address (the
robot at the address its claim resolved, when given). Mock
mode (the only place allowed to build simulated devices): the simulated cell, and for
each device its family's twin — a protocol-level server on a loopback address that
serves what the configured device would — with the *same* driver built from the options
pointed at the twin; a family without a twin is an in-process simulation, which only
mock mode accepts. Every robot goes behind the safety gate. Every DeviceError of the
building and connecting names its device (``device``: "robot", a sensor's name).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cellcal.calib.robot_model import RobotModel
from cellcal.campaign.engine import SensorSetting
from cellcal.clock import Clock
from cellcal.config import CellConfig
from cellcal.device_options import RobotOptions, SensorOptions
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, PositionSensor, Robot
from cellcal.drivers.safety import GuardedRobot
from cellcal.errors import DeviceError, device_errors
from cellcal.families import ROBOT, Family, find, load


@dataclass(frozen=True)
class Devices:
    robot: Robot
    sensors: tuple[SensorSetting, ...]
    simulated_cell: object | None  # the mock cell's truth, for tests and reports
    servers: tuple[Closeable, ...] = ()  # the twins (mock mode)

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


def family_of(options: RobotOptions | SensorOptions) -> Family:
    """The family of a configured device (the configuration only holds known ones)."""
    if isinstance(options, RobotOptions):
        f = find("robot", ROBOT, options.driver)
    else:
        f = find("sensor", options.kind, options.driver)
    if f is None:  # pragma: no cover - config validation admits only registered families
        raise DeviceError(
            f"no device family for driver {options.driver!r}", device=device_name(options)
        )
    return f


def _where(options: RobotOptions | SensorOptions) -> str:
    return "robot" if isinstance(options, RobotOptions) else f"sensor {options.name}"


def device_name(options: RobotOptions | SensorOptions) -> str:
    """The device's name in the configuration: what its DeviceErrors name."""
    return ROBOT_NAME if isinstance(options, RobotOptions) else options.name


def _build(
    options: RobotOptions | SensorOptions,
    context: DeviceContext,
    *,
    mock: bool,
    time_scale: float,
    servers: list[Closeable],
) -> Any:
    """One device, by its family: in mock mode through its twin."""
    family = family_of(options)
    if mock and family.twin is not None:
        with device_errors(device_name(options)):  # the twin is the device in mock mode
            twin = load(family.twin)(options, context.cell, time_scale)
        servers.append(twin)
        options = twin.options
    elif not mock:
        if family.mock_only:
            raise DeviceError(
                f'{_where(options)}: driver = "{family.driver}" is {family.summary}; '
                "it needs --mock",
                device=device_name(options),
            )
        if not (options.endpoint() if isinstance(options, SensorOptions) else options.address):
            what = "controller" if family.role == "robot" else "sensor"
            raise DeviceError(
                f"{_where(options)}.address is empty: where is the {what} "
                f'(driver = "{family.driver}")?',
                device=device_name(options),
            )
    with device_errors(device_name(options)):
        return family.device_class().from_options(options, context)


def build_devices(
    config: CellConfig,
    nominal: RobotModel,
    clock: Clock,
    *,
    mock: bool,
    seed: int | None,
    noise_stream: int = 0,
    robot_address: str | None = None,
    report: Callable[[str, str], None] | None = None,
) -> Devices:
    """Connect the configured devices, or in mock mode their twins'. ``robot_address``
    (real mode): where the robot's driver connects instead of ``robot.address`` as
    written — the address the robot's claim resolved it to
    (:func:`cellcal.campaign.locks.claimed_address`), so that a name is not resolved a
    second time, perhaps to another machine. ``report(device, message)``: where a device
    that takes long to get ready says what it is doing (``DeviceContext.report``)."""
    cell = None
    if mock:
        from cellcal.families import SimulatedCell

        cell = SimulatedCell(config, nominal, seed, noise_stream, clock)
    context = DeviceContext(clock, cell, report)
    time_scale = float(getattr(clock, "time_scale", 0.0))
    servers: list[Closeable] = []
    opened: list[PositionSensor] = []
    try:
        robot_options = config.robot
        if robot_address and not mock:
            robot_options = robot_options.model_copy(update={"address": robot_address})
        robot = _guarded(
            _build(robot_options, context, mock=mock, time_scale=time_scale, servers=servers),
            config,
            nominal,
        )
        sensors: list[SensorSetting] = []
        for s in config.sensor:
            sensor = _build(s, context, mock=mock, time_scale=time_scale, servers=servers)
            with device_errors(s.name):
                sensor.connect()
            opened.append(sensor)
            sensors.append(SensorSetting(sensor, s.rate_hz))
        with device_errors(ROBOT_NAME):
            robot.connect()
    except BaseException:
        for sensor in opened:
            with contextlib.suppress(Exception):
                sensor.close()
        for srv in servers:
            with contextlib.suppress(Exception):
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
