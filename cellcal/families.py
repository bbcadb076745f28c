"""The device families cellcal knows: one table, read by the configuration (each
device section's options), the device factory (the driver, and in mock mode the twin),
``cellcal mock`` (a command per twin) and the contract test suites; and the camera
backends of the photogrammetry rig, a second table read the same way.

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
  line naming the extra that brings it;
* ``mock``, ``mock_command`` — ``cellcal mock <mock>`` serves the twin on its own (the
  driver's name when not given): the click command at ``mock_command``, or without one
  a command made from the line (:func:`cellcal.commands.mock.family_command`);
* ``simulated_as`` — what the simulated cell gives a sensor's twin: ``point`` (the
  target's position, placed and with the noise of ``[simulation]``'s tracker) or
  ``images`` (placed where ``[simulation]`` puts the rig; its twin renders them).

Adding a family: a driver module, a twin module, one line below — or, outside cellcal,
a distribution whose entry point of the group :data:`GROUP` (``cellcal.families``) is a
:class:`Family` or a sequence of them (:func:`installed`): docs/device-families.md.

This module is also the registry of the twins: the one module outside ``cellcal.mocks``
that imports it (the import contract's one exception, ``[tool.importlinter]`` in
``pyproject.toml``). The table's twins, and the few names of ``cellcal.mocks`` that the
rest of cellcal uses (:data:`TWIN_NAMES`: ``from cellcal.families import SimulatedCell``),
are imported only when first asked for, so a real cell's run loads none of it.

Size (about 500 lines): the table and the lazy imports of the twins it names grow by a
few lines per family; split the twin registry (``TWIN_NAMES``, ``twin_module``) into a
module of its own when another family comes.
"""

from __future__ import annotations

import importlib
import re
import sys
import threading
from dataclasses import dataclass, field, replace
from importlib.metadata import EntryPoint, entry_points
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

from cellcal.errors import UserError
from cellcal.extras import PROVIDERS, needs, require

if TYPE_CHECKING:  # what ``__getattr__`` hands out, for the type checker
    from cellcal.mocks.abb.rws_server import RwsTwin as RwsTwin
    from cellcal.mocks.fanuc.rmi_server import RmiTwin as RmiTwin
    from cellcal.mocks.kuka.eki_server import EkiTwin as EkiTwin
    from cellcal.mocks.kuka.krc import krc_for_cell as krc_for_cell
    from cellcal.mocks.kuka.kvp_server import KvpTwin as KvpTwin
    from cellcal.mocks.modbus.server import ModbusRobotFaults as ModbusRobotFaults
    from cellcal.mocks.modbus.server import ModbusRobotTwin as ModbusRobotTwin
    from cellcal.mocks.modbus.server import xyzabc as xyzabc
    from cellcal.mocks.rig.board_views import BoardScene as BoardScene
    from cellcal.mocks.rig.capture_twin import mock_rig as mock_rig
    from cellcal.mocks.rig.gige_cameras import GigECameraTwin as GigECameraTwin
    from cellcal.mocks.rig.twin import RenderedRig as RenderedRig
    from cellcal.mocks.rig.twin import RigScene as RigScene
    from cellcal.mocks.rig.twin import RigTruth as RigTruth
    from cellcal.mocks.simulated_cell import SimulatedCell as SimulatedCell
    from cellcal.mocks.tracker.emscon_server import emscon_twin as emscon_twin
    from cellcal.mocks.tracker.server import TrackerFaults as TrackerFaults
    from cellcal.mocks.tracker.server import TrackerTwin as TrackerTwin
    from cellcal.mocks.twins import limits_deg as limits_deg
    from cellcal.mocks.ur.server import twin_for_cell as twin_for_cell
    from cellcal.mocks.yaskawa.hses_server import HsesTwin as HsesTwin

Role = Literal["robot", "sensor"]

#: Robots have no kind of their own in the configuration: their family is the driver.
ROBOT = "robot"


class FamilyError(UserError):
    """A family of an installed distribution that cannot be used: the line names its
    entry point (:attr:`Family.origin`)."""


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
    mock: str = ""
    mock_command: str | None = None
    simulated_as: Literal["point", "images"] = "point"
    #: where the line comes from: "" for cellcal's table; for a distribution's, its entry
    #: point (set by :func:`installed`, whatever the distribution wrote)
    origin: str = field(default="", compare=False)

    @property
    def tag(self) -> str:
        """The family's name in messages and in the configuration's discriminator."""
        return self.driver if self.role == "robot" else f"{self.kind}/{self.driver}"

    @property
    def feature(self) -> str:
        """The family in a missing library's line: ``the robot driver "ur"``."""
        return f'the {self.role if self.role == "robot" else self.kind} driver "{self.driver}"'

    @property
    def mock_name(self) -> str | None:
        """Its ``cellcal mock`` subcommand; None for a family without a twin."""
        return None if self.twin is None else self.mock or self.driver

    def options_model(self) -> Any:
        model = load(self.options)
        if self.origin:
            _check_options(self, model)
        return model

    def device_class(self) -> Any:
        return load(self.device)

    def require(self) -> None:
        """Import the driver's optional libraries (:attr:`libraries`) now: cellcal's own
        through its extras; a distribution's others by name, a missing one a line
        naming its entry point."""
        if not self.origin:
            require(self.feature, *self.libraries)
            return
        require(self.feature, *(m for m in self.libraries if m in PROVIDERS))
        for module in self.libraries:
            if module not in PROVIDERS:
                try:
                    importlib.import_module(module)
                except ImportError:
                    raise FamilyError(
                        f"{self.feature} needs {module}, which is not installed "
                        f"(the family of {self.origin})"
                    ) from None


FAMILIES: tuple[Family, ...] = (
    Family("robot", ROBOT, "simulated", "cellcal.device_options:SimulatedRobotOptions", "cellcal.mocks.simulated_devices:SimulatedRobot", None, "the simulated cell's robot, in-process", mock_only=True),  # noqa: E501
    Family("robot", ROBOT, "modbus", "cellcal.drivers.modbus_options:ModbusRobotOptions", "cellcal.drivers.modbus_robot:ModbusRobot", "cellcal.mocks.modbus.server:serve", "a controller behind Modbus TCP with the handshake map of docs/robots.md", libraries=("pymodbus",), mock="modbus-robot", mock_command="cellcal.commands.mock:mock_modbus_robot"),  # noqa: E501
    Family("robot", ROBOT, "ur", "cellcal.drivers.ur:UROptions", "cellcal.drivers.ur:URRobot", "cellcal.mocks.ur.server:serve", "a Universal Robots e-Series controller through ur_rtde", libraries=("rtde_control", "rtde_receive"), mock_command="cellcal.commands.mock:mock_ur"),  # noqa: E501
    Family("robot", ROBOT, "kuka-kvp", "cellcal.drivers.kuka_kvp:KukaKvpOptions", "cellcal.drivers.kuka_kvp:KukaKvpRobot", "cellcal.mocks.kuka.kvp_server:serve", "a KUKA KR C4/C5 through KUKAVARPROXY (TCP 7000) and cellcal's KRL loop (docs/robots.md)", mock_command="cellcal.commands.mock_robots:mock_kuka_kvp"),  # noqa: E501
    Family("robot", ROBOT, "kuka-eki", "cellcal.drivers.kuka_eki:KukaEkiOptions", "cellcal.drivers.kuka_eki:KukaEkiRobot", "cellcal.mocks.kuka.eki_server:serve", "a KUKA KR C4/C5 through the EthernetKRL option and cellcal's KRL program (docs/robots.md)", mock_command="cellcal.commands.mock_robots:mock_kuka_eki"),  # noqa: E501
    Family("robot", ROBOT, "abb-rws", "cellcal.drivers.abb_rws:AbbRwsOptions", "cellcal.drivers.abb_rws:AbbRwsRobot", "cellcal.mocks.abb.rws_server:serve", "an ABB IRC5 (RobotWare 6) or OmniCore (RobotWare 7) through Robot Web Services and cellcal's RAPID module (docs/robots.md)", libraries=("httpx",), mock_command="cellcal.commands.mock_robots:mock_abb_rws"),  # noqa: E501
    Family("robot", ROBOT, "fanuc-rmi", "cellcal.drivers.fanuc_rmi:FanucRmiOptions", "cellcal.drivers.fanuc_rmi:FanucRmiRobot", "cellcal.mocks.fanuc.rmi_server:serve", "a FANUC R-30iB Plus or R-30iB Mate Plus through the Remote Motion Interface option (TCP 16001; docs/robots.md)", mock_command="cellcal.commands.mock_robots:mock_fanuc_rmi"),  # noqa: E501
    Family("robot", ROBOT, "yaskawa-hses", "cellcal.drivers.yaskawa_hses:YaskawaHsesOptions", "cellcal.drivers.yaskawa_hses:YaskawaHsesRobot", "cellcal.mocks.yaskawa.hses_server:serve", "a Yaskawa Motoman (DX100, DX200, FS100, YRC1000) through the High-Speed Ethernet Server (UDP 10040; docs/robots.md)", mock_command="cellcal.commands.mock_robots:mock_yaskawa_hses"),  # noqa: E501
    Family("sensor", "laser-tracker", "line-protocol", "cellcal.drivers.tracker:LineTrackerOptions", "cellcal.drivers.tracker:LineTracker", "cellcal.mocks.tracker.server:serve", "a laser tracker speaking cellcal's line protocol over serial or TCP (docs/tracker.md)", mock="tracker", mock_command="cellcal.commands.mock:mock_tracker"),  # noqa: E501
    Family("sensor", "laser-tracker", "emscon", "cellcal.drivers.emscon:EmsconOptions", "cellcal.drivers.emscon:EmsconTracker", "cellcal.mocks.tracker.emscon_server:serve", "a Leica laser tracker (AT401, AT402, AT403) through its emScon TPI interface on TCP (docs/tracker.md)", mock="tracker", mock_command="cellcal.commands.mock:mock_tracker"),  # noqa: E501
    Family("sensor", "photogrammetry", "cameras", "cellcal.drivers.photogrammetry:CameraRigOptions", "cellcal.drivers.photogrammetry:CameraRigSensor", "cellcal.mocks.rig.twin:serve", "a photogrammetry rig of cameras: marker corners, the target's pose from every camera (docs/photogrammetry.md)", libraries=("cv2",), mock_command="cellcal.commands.rig_capture:mock_cameras", simulated_as="images"),  # noqa: E501
)  # fmt: skip


@dataclass(frozen=True)
class CameraBackend:
    """A camera backend of the photogrammetry rig (``backend`` in ``[sensor.capture]``):
    ``options``, its rig options (a :class:`~cellcal.drivers.cameras.backends.RigOptions`
    with ``backend`` a one-value ``Literal``); ``rig``, the rig class
    (``from_options(options, clock=None)``); ``twin``, mock mode's cameras speaking its
    protocol, ``serve(options, scene)`` (the sensor's options and a scene whose frames
    they serve; its ``options`` are the capture's, pointed at the twin), or ``None``
    when mock mode renders its frames in-process; ``unavailable``, a function that says
    why the twin cannot run here (one line; None when it can); ``mock_only``, a backend
    no configuration may name."""

    name: str
    options: str
    rig: str
    twin: str | None
    summary: str
    libraries: tuple[str, ...] = ()
    unavailable: str | None = None
    mock_only: bool = False

    @property
    def feature(self) -> str:
        return f'the camera backend "{self.name}"'

    def require(self) -> None:
        require(self.feature, *self.libraries)


CAMERA_BACKENDS: tuple[CameraBackend, ...] = (
    CameraBackend("aravis", "cellcal.drivers.cameras.aravis:AravisRigOptions", "cellcal.drivers.cameras.aravis:AravisRig", "cellcal.mocks.rig.twin:serve_gige", "GigE Vision and USB3 Vision cameras of any vendor, through Aravis 0.8 (PyGObject and Debian's packages: the cameras extra, checked as it connects)", unavailable="cellcal.drivers.cameras.aravis:aravis_missing"),  # noqa: E501
    CameraBackend("opencv", "cellcal.drivers.cameras.opencv:OpenCVRigOptions", "cellcal.drivers.cameras.opencv:OpenCVRig", None, "UVC devices, RTSP and HTTP/MJPEG cameras through cv2.VideoCapture", libraries=("cv2",)),  # noqa: E501
    CameraBackend("files", "cellcal.drivers.cameras.files:FilesRigOptions", "cellcal.drivers.cameras.files:FilesRig", None, "recorded image sets played back, <camera>.png in a folder per set", libraries=("cv2",)),  # noqa: E501
    CameraBackend("rendered", "cellcal.mocks.rig.twin:RenderedRigOptions", "cellcal.mocks.rig.twin:RenderedRig", None, "mock mode's in-process cameras: the simulated cell's frames rendered", libraries=("cv2",), mock_only=True),  # noqa: E501
)  # fmt: skip


def camera_backends(*, configurable: bool = False) -> tuple[CameraBackend, ...]:
    """The table's rows (``configurable``: those a configuration may name)."""
    return tuple(b for b in CAMERA_BACKENDS if not (configurable and b.mock_only))


def camera_backend(name: str) -> CameraBackend | None:
    return next((b for b in CAMERA_BACKENDS if b.name == name), None)


def load(path: str, *, libraries: bool = True) -> Any:
    """Import ``module:attribute``: a module of ``cellcal.mocks`` through
    :func:`twin_module`; a driver, a twin, a rig class of the tables with its optional
    libraries (``libraries=False``: without), a missing one in one line naming its
    extra. A distribution's family that cannot be imported is a line naming its entry
    point."""
    module, _, attribute = path.partition(":")
    owner = _owner(path)
    try:
        with needs(owner.feature if owner is not None else path):
            if libraries and owner is not None and path not in (owner.options, _command(owner)):
                owner.require()
            if module.startswith(MOCKS):
                return getattr(twin_module(module.removeprefix(MOCKS)), attribute)
            return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as exc:
        if isinstance(owner, Family) and owner.origin:
            raise FamilyError(f"{owner.origin}: cannot load {path} ({_one_line(exc)})") from None
        raise


def _owner(path: str) -> Family | CameraBackend | None:
    for f in registered():
        if path in (f.options, f.device, f.twin, f.mock_command):
            return f
    return next((b for b in CAMERA_BACKENDS if path in (b.options, b.rig, b.twin)), None)


def _command(owner: Family | CameraBackend) -> str | None:
    return owner.mock_command if isinstance(owner, Family) else None


def registered() -> tuple[Family, ...]:
    """Every family: cellcal's table, then those of installed distributions."""
    return (*FAMILIES, *installed())


def families(role: Role) -> tuple[Family, ...]:
    return tuple(f for f in registered() if f.role == role)


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


# --------------------------------------------------- families of other distributions

#: The entry point group a distribution registers its families in.
GROUP = "cellcal.families"
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
_PATH = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


def warn(line: str) -> None:
    """A refused entry point, in one line on stderr (as the command line warns)."""
    print(f"cellcal: warning: {line}", file=sys.stderr)


#: The distributions' families once loaded (:func:`installed`).
_INSTALLED: list[tuple[Family, ...]] = []
_LOADING = threading.RLock()


def installed() -> tuple[Family, ...]:
    """The families that installed distributions register: each entry point of the
    group :data:`GROUP` is a :class:`Family` or a sequence of them, loaded once (the
    first time a family is looked up). One that cannot be imported, is no Family, or
    clashes with a family or a ``cellcal mock`` command already registered is refused
    in one line through :func:`warn`, and the others, cellcal's own first, stay."""
    with _LOADING:
        if not _INSTALLED:
            _INSTALLED.append(())  # a lookup while an entry point imports sees none yet
            _INSTALLED[0] = _load_installed()
        return _INSTALLED[0]


def _load_installed() -> tuple[Family, ...]:
    accepted: list[Family] = []
    for ep in entry_points(group=GROUP):
        origin = _origin(ep)
        try:
            found = _families_in(ep)
        except Exception as exc:  # a distribution's bug must not stop cellcal's families
            warn(f"{origin} refused: {_one_line(exc)}")
            continue
        for family in found:
            why = _refusal(family, (*FAMILIES, *accepted))
            if why is not None:
                warn(f"{origin} refused: {why}")
            else:
                accepted.append(replace(family, origin=origin))
    return tuple(accepted)


def _origin(ep: EntryPoint) -> str:
    dist = f" ({ep.dist.name} {ep.dist.version})" if ep.dist is not None else ""
    return f"entry point {ep.name} = {ep.value}{dist}"


def _families_in(ep: EntryPoint) -> tuple[Family, ...]:
    try:
        value = ep.load()
    except Exception as exc:
        raise FamilyError(f"cannot import it ({type(exc).__name__}: {exc})") from None
    found = (value,) if isinstance(value, Family) else value
    if not isinstance(found, list | tuple) or not all(isinstance(f, Family) for f in found):
        raise FamilyError(
            f"its value is of type {type(value).__name__}, not a cellcal.families.Family "
            "or a sequence of them"
        )
    return tuple(found)


def _refusal(f: Family, taken: tuple[Family, ...]) -> str | None:
    """Why a distribution's family cannot join ``taken``, or None."""
    if f.role not in ("robot", "sensor"):
        return f"role {f.role!r}: robot or sensor"
    if f.role == "robot" and f.kind != ROBOT:
        return f"a robot's kind is {ROBOT!r}, not {f.kind!r}"
    names = [("kind", f.kind), ("driver", f.driver)] + ([("mock", f.mock)] if f.mock else [])
    for what, value in names:
        if not isinstance(value, str) or not _NAME.match(value):
            return f"{what} {value!r}: letters, digits, '_', '.', '-'"
    paths = [("options", f.options), ("device", f.device)]
    paths += [(k, p) for k, p in (("twin", f.twin), ("mock_command", f.mock_command)) if p]
    for what, path in paths:
        if not isinstance(path, str) or not _PATH.match(path) or path.startswith(MOCKS):
            return f"{what} {path!r}: module:attribute of the distribution's own"
    if (f.twin is None) != f.mock_only:
        return f"{f.tag}: a family without a twin is mock_only, one with a twin is not"
    if f.simulated_as not in ("point", "images"):
        return f"simulated_as {f.simulated_as!r}: point or images"
    if not isinstance(f.libraries, tuple) or not all(isinstance(m, str) for m in f.libraries):
        return "libraries: a tuple of module names"
    for other in taken:
        by = other.origin or "cellcal"
        if (other.role, other.kind, other.driver) == (f.role, f.kind, f.driver):
            return f"the {f.role} family {f.tag} is {by}'s already"
        if f.mock_name is not None and other.mock_name == f.mock_name:
            return f'cellcal mock {f.mock_name} is {by}\'s already ({other.tag}); set mock = "…"'
    return None


def _check_options(f: Family, model: Any) -> None:
    """A distribution's options model, checked when first loaded."""
    from cellcal.device_options import RobotOptions, SensorOptions

    base = RobotOptions if f.role == "robot" else SensorOptions
    why = None
    if not isinstance(model, type) or not issubclass(model, base):
        why = f"is not a subclass of cellcal.device_options.{base.__name__}"
    elif model.model_fields["driver"].default != f.driver:
        why = f"has driver {model.model_fields['driver'].default!r}, not {f.driver!r}"
    elif f.role == "sensor" and model.model_fields["kind"].default != f.kind:
        why = f"has kind {model.model_fields['kind'].default!r}, not {f.kind!r}"
    if why is not None:
        raise FamilyError(f"{f.origin}: options {f.options} {why}")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# ------------------------------------------------------------------------- the twins

MOCKS = "cellcal.mocks."

#: The names of ``cellcal.mocks`` the rest of cellcal uses besides the table's twins, and
#: their modules: ``from cellcal.families import SimulatedCell`` imports its module on
#: first use (PEP 562, :func:`__getattr__`).
TWIN_NAMES = {
    # the simulated cell, the truth every twin serves (the device factory in mock mode)
    "SimulatedCell": "simulated_cell",
    # cellcal mock tracker | modbus-robot | ur
    "TrackerTwin": "tracker.server",
    "TrackerFaults": "tracker.server",
    "emscon_twin": "tracker.emscon_server",
    "ModbusRobotTwin": "modbus.server",
    "ModbusRobotFaults": "modbus.server",
    "xyzabc": "modbus.server",
    "limits_deg": "twins",
    "twin_for_cell": "ur.server",
    # cellcal mock kuka-kvp | kuka-eki
    "KvpTwin": "kuka.kvp_server",
    "EkiTwin": "kuka.eki_server",
    "krc_for_cell": "kuka.krc",
    # cellcal mock abb-rws
    "RwsTwin": "abb.rws_server",
    # cellcal mock fanuc-rmi
    "RmiTwin": "fanuc.rmi_server",
    # cellcal mock yaskawa-hses
    "HsesTwin": "yaskawa.hses_server",
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
    if name == "tracker.emscon_server":
        from cellcal.mocks.tracker import emscon_server

        return emscon_server
    if name == "modbus.server":
        from cellcal.mocks.modbus import server as modbus_robot_server

        return modbus_robot_server
    if name == "ur.server":
        from cellcal.mocks.ur import server as ur_server

        return ur_server
    if name == "kuka.kvp_server":
        from cellcal.mocks.kuka import kvp_server

        return kvp_server
    if name == "kuka.eki_server":
        from cellcal.mocks.kuka import eki_server

        return eki_server
    if name == "abb.rws_server":
        from cellcal.mocks.abb import rws_server

        return rws_server
    if name == "fanuc.rmi_server":
        from cellcal.mocks.fanuc import rmi_server

        return rmi_server
    if name == "yaskawa.hses_server":
        from cellcal.mocks.yaskawa import hses_server

        return hses_server
    if name == "kuka.krc":
        from cellcal.mocks.kuka import krc

        return krc
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
