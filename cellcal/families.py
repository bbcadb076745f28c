"""The device families cellcal knows: one table, read by the configuration (each
device section's options), the device factory (the driver, and in mock mode the twin)
and the contract test suites.

A family is a role (robot or sensor), a kind and a driver. Its line names, as
``module:attribute`` strings imported only when needed (python-can's interface table,
pyserial's URL handlers):

* ``options`` — a pydantic model, subclass of :class:`~cellcal.device_options.RobotOptions`
  or :class:`~cellcal.device_options.SensorOptions`, whose ``driver`` (and ``kind``) is a
  one-value ``Literal``: the keys of the device's table in the configuration file;
* ``device`` — the driver class, with ``from_options(options, context)`` (a
  :class:`~cellcal.drivers.base.DeviceContext`), behind the ``Robot`` or
  ``PositionSensor`` Protocol of ``drivers/base.py``;
* ``twin`` — in mock mode, ``serve(options, cell, time_scale)`` starts the protocol-level
  twin of the configured device on a loopback address and returns it; its ``options``
  are the configured ones pointed at the twin, and the same driver is built from them.
  ``None`` for an in-process simulation (``mock_only``: refused without ``--mock``).

Adding a family: a driver module, a twin module, one line below (``docs/device-families.md``).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Literal

Role = Literal["robot", "sensor"]

#: Robots have no kind of their own in the configuration: their family is the driver.
ROBOT = "robot"


@dataclass(frozen=True)
class Family:
    role: Role
    kind: str
    driver: str
    options: str
    device: str
    twin: str | None
    summary: str
    mock_only: bool = False

    @property
    def tag(self) -> str:
        """The family's name in messages and in the configuration's discriminator."""
        return self.driver if self.role == "robot" else f"{self.kind}/{self.driver}"

    def options_model(self) -> Any:
        return load(self.options)

    def device_class(self) -> Any:
        return load(self.device)


FAMILIES: tuple[Family, ...] = (
    Family("robot", ROBOT, "simulated", "cellcal.device_options:SimulatedRobotOptions", "cellcal.mocks.simulated_devices:SimulatedRobot", None, "the simulated cell's robot, in-process", mock_only=True),  # noqa: E501
    Family("robot", ROBOT, "modbus", "cellcal.drivers.modbus_robot:ModbusRobotOptions", "cellcal.drivers.modbus_robot:ModbusRobot", "cellcal.mocks.modbus_robot_server:serve", "a controller behind Modbus TCP with the handshake map of docs/robots.md"),  # noqa: E501
    Family("robot", ROBOT, "ur", "cellcal.drivers.ur:UROptions", "cellcal.drivers.ur:URRobot", "cellcal.mocks.ur_server:serve", "a Universal Robots e-Series controller through ur_rtde"),  # noqa: E501
    Family("sensor", "laser-tracker", "line-protocol", "cellcal.drivers.tracker:LineTrackerOptions", "cellcal.drivers.tracker:LineTracker", "cellcal.mocks.tracker_server:serve", "a laser tracker speaking cellcal's line protocol over serial or TCP (docs/tracker.md)"),  # noqa: E501
    Family("sensor", "photogrammetry", "cameras", "cellcal.drivers.photogrammetry:CameraRigOptions", "cellcal.drivers.photogrammetry:CameraRigSensor", "cellcal.mocks.rig_twin:serve", "a photogrammetry rig of cameras: marker corners, the target's pose from every camera (docs/photogrammetry.md)"),  # noqa: E501
)  # fmt: skip


def load(path: str) -> Any:
    """Import ``module:attribute``."""
    module, _, attribute = path.partition(":")
    return getattr(importlib.import_module(module), attribute)


def families(role: Role) -> tuple[Family, ...]:
    return tuple(f for f in FAMILIES if f.role == role)


def kinds(role: Role) -> tuple[str, ...]:
    return tuple(dict.fromkeys(f.kind for f in families(role)))


def default_driver(role: Role, kind: str) -> str | None:
    """The driver a section gets when it names none: the first of its kind in the table."""
    return next((f.driver for f in families(role) if f.kind == kind), None)


def find(role: Role, kind: str, driver: str) -> Family | None:
    return next(
        (f for f in families(role) if f.kind == kind and f.driver == driver),
        None,
    )
