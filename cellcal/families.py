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
  ``None`` for an in-process simulation (``mock_only``: refused without ``--mock``);
* ``libraries`` — the optional libraries the driver needs (``cellcal/extras.py``),
  imported before the driver is built or its twin started: a missing one ends in one
  line naming the extra that brings it.

Adding a family: a driver module, a twin module, one line below (``docs/device-families.md``).

This module is also the registry of the twins: the one module outside ``cellcal.mocks``
that imports it (the import contract's one exception, ``[tool.importlinter]`` in
``pyproject.toml``). The table's twins, and the few names of ``cellcal.mocks`` that the
rest of cellcal uses (:data:`TWIN_NAMES`: ``from cellcal.families import SimulatedCell``),
are imported only when first asked for, so a real cell's run loads none of it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

from cellcal.extras import needs, require

if TYPE_CHECKING:  # what ``__getattr__`` hands out, for the type checker
    from cellcal.mocks.modbus.server import ModbusRobotFaults as ModbusRobotFaults
    from cellcal.mocks.modbus.server import ModbusRobotSimulator as ModbusRobotSimulator
    from cellcal.mocks.modbus.server import xyzabc as xyzabc
    from cellcal.mocks.rig.board_views import BoardScene as BoardScene
    from cellcal.mocks.rig.capture_twin import mock_rig as mock_rig
    from cellcal.mocks.rig.gige_cameras import GigECameraTwin as GigECameraTwin
    from cellcal.mocks.rig.twin import RenderedRig as RenderedRig
    from cellcal.mocks.rig.twin import RigScene as RigScene
    from cellcal.mocks.rig.twin import RigTruth as RigTruth
    from cellcal.mocks.simulated_cell import SimulatedCell as SimulatedCell
    from cellcal.mocks.tracker.server import MockTracker as MockTracker
    from cellcal.mocks.tracker.server import TrackerFaults as TrackerFaults
    from cellcal.mocks.twins import limits_deg as limits_deg
    from cellcal.mocks.ur.server import simulator_for_cell as simulator_for_cell

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
    libraries: tuple[str, ...] = ()

    @property
    def tag(self) -> str:
        """The family's name in messages and in the configuration's discriminator."""
        return self.driver if self.role == "robot" else f"{self.kind}/{self.driver}"

    @property
    def feature(self) -> str:
        """The family in a missing library's line: ``the robot driver "ur"``."""
        return f'the {self.role if self.role == "robot" else self.kind} driver "{self.driver}"'

    def options_model(self) -> Any:
        return load(self.options)

    def device_class(self) -> Any:
        return load(self.device)

    def require(self) -> None:
        """Import the driver's optional libraries (:attr:`libraries`) now."""
        require(self.feature, *self.libraries)


FAMILIES: tuple[Family, ...] = (
    Family("robot", ROBOT, "simulated", "cellcal.device_options:SimulatedRobotOptions", "cellcal.mocks.simulated_devices:SimulatedRobot", None, "the simulated cell's robot, in-process", mock_only=True),  # noqa: E501
    Family("robot", ROBOT, "modbus", "cellcal.drivers.modbus_robot:ModbusRobotOptions", "cellcal.drivers.modbus_robot:ModbusRobot", "cellcal.mocks.modbus.server:serve", "a controller behind Modbus TCP with the handshake map of docs/robots.md", libraries=("pymodbus",)),  # noqa: E501
    Family("robot", ROBOT, "ur", "cellcal.drivers.ur:UROptions", "cellcal.drivers.ur:URRobot", "cellcal.mocks.ur.server:serve", "a Universal Robots e-Series controller through ur_rtde", libraries=("rtde_control", "rtde_receive")),  # noqa: E501
    Family("sensor", "laser-tracker", "line-protocol", "cellcal.drivers.tracker:LineTrackerOptions", "cellcal.drivers.tracker:LineTracker", "cellcal.mocks.tracker.server:serve", "a laser tracker speaking cellcal's line protocol over serial or TCP (docs/tracker.md)"),  # noqa: E501
    Family("sensor", "photogrammetry", "cameras", "cellcal.drivers.photogrammetry:CameraRigOptions", "cellcal.drivers.photogrammetry:CameraRigSensor", "cellcal.mocks.rig.twin:serve", "a photogrammetry rig of cameras: marker corners, the target's pose from every camera (docs/photogrammetry.md)", libraries=("cv2",)),  # noqa: E501
)  # fmt: skip


def load(path: str) -> Any:
    """Import ``module:attribute``: a module of ``cellcal.mocks`` through
    :func:`twin_module`; a driver or twin of the table with its family's optional
    libraries (:meth:`Family.require`), a missing one in one line naming its extra."""
    module, _, attribute = path.partition(":")
    family = next((f for f in FAMILIES if path in (f.options, f.device, f.twin)), None)
    with needs(family.feature if family is not None else path):
        if family is not None and path != family.options:
            family.require()
        if module.startswith(MOCKS):
            return getattr(twin_module(module.removeprefix(MOCKS)), attribute)
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


# ------------------------------------------------------------------------- the twins

MOCKS = "cellcal.mocks."

#: The names of ``cellcal.mocks`` the rest of cellcal uses besides the table's twins, and
#: their modules: ``from cellcal.families import SimulatedCell`` imports its module on
#: first use (PEP 562, :func:`__getattr__`).
TWIN_NAMES = {
    # the simulated cell, the truth every twin serves (the device factory in mock mode)
    "SimulatedCell": "simulated_cell",
    # cellcal mock tracker | modbus-robot | ur
    "MockTracker": "tracker.server",
    "TrackerFaults": "tracker.server",
    "ModbusRobotSimulator": "modbus.server",
    "ModbusRobotFaults": "modbus.server",
    "xyzabc": "modbus.server",
    "limits_deg": "twins",
    "simulator_for_cell": "ur.server",
    # cellcal rig capture --mock, cellcal mock cameras
    "mock_rig": "rig.capture_twin",
    "GigECameraTwin": "rig.gige_cameras",
    "BoardScene": "rig.board_views",
    "RigScene": "rig.twin",
    "RigTruth": "rig.twin",
    # the camera driver's in-process backend in mock mode (cameras.rig_class("rendered"))
    "RenderedRig": "rig.twin",
}


def twin_module(name: str) -> ModuleType:
    """``cellcal.mocks.<name>`` (``tracker.server``), imported now if it is not yet: one
    of the modules the registry hands out (the table's twins, :data:`TWIN_NAMES`), each
    import spelled out so that the import contract sees it."""
    if name == "simulated_cell":
        from cellcal.mocks import simulated_cell

        return simulated_cell
    if name == "simulated_devices":
        from cellcal.mocks import simulated_devices

        return simulated_devices
    if name == "twins":
        from cellcal.mocks import twins

        return twins
    if name == "tracker.server":
        from cellcal.mocks.tracker import server as tracker_server

        return tracker_server
    if name == "modbus.server":
        from cellcal.mocks.modbus import server as modbus_robot_server

        return modbus_robot_server
    if name == "ur.server":
        from cellcal.mocks.ur import server as ur_server

        return ur_server
    if name == "rig.twin":
        from cellcal.mocks.rig import twin as rig_twin

        return rig_twin
    if name == "rig.capture_twin":
        from cellcal.mocks.rig import capture_twin as rig_capture_twin

        return rig_capture_twin
    if name == "rig.board_views":
        from cellcal.mocks.rig import board_views

        return board_views
    if name == "rig.gige_cameras":
        from cellcal.mocks.rig import gige_cameras

        return gige_cameras
    raise ValueError(f"{MOCKS}{name}: not a module the registry of twins hands out")


if not TYPE_CHECKING:

    def __getattr__(name: str) -> Any:
        """A name of :data:`TWIN_NAMES`, its module imported on first use."""
        if name not in TWIN_NAMES:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        return getattr(twin_module(TWIN_NAMES[name]), name)
