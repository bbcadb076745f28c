"""Facts, not text: every DeviceError a driver raises names its device (``device``: its
name in the configuration — "robot", a sensor's name), the messages as they were; and
every driver describes its device (``describe()``) with what its protocol tells, against
the twins. Sockets: the twins listen on 127.0.0.181–127.0.0.190 (the cameras' inside a
network namespace of their own), each started before it is asked anything."""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.clock import SimulatedClock
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription
from cellcal.drivers.cameras.files import FilesRig, FilesRigOptions
from cellcal.drivers.modbus_robot import ModbusRobot
from cellcal.drivers.photogrammetry import CameraRigSensor
from cellcal.drivers.safety import GuardedRobot, SafetyError
from cellcal.drivers.tracker import LineTracker
from cellcal.drivers.tracker_protocol import BeamBrokenError, TrackerError
from cellcal.drivers.transport import TransportError
from cellcal.drivers.ur import URRobot
from cellcal.errors import (
    CampaignError,
    DeviceError,
    NoTargetError,
    UserError,
    device_errors,
    device_of,
)
from cellcal.files.images import write_image
from cellcal.files.models import load_model
from cellcal.files.photogrammetry import read_rig, read_target
from cellcal.mocks.modbus.server import ModbusRobotTwin
from cellcal.mocks.modbus.state import ModbusRobotFaults
from cellcal.mocks.simulated_devices import SimulatedRobot
from cellcal.mocks.tracker.server import FIRMWARE, MAKER, MODEL, TrackerTwin
from tests.drivers.scripted import ScriptedTransport

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60)]

HOME_DEG = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
IDN = ("*IDN?", ["OK Leica,AT960,SN-12,2.4"])


def _raised(call: object, *args: object) -> DeviceError:
    with pytest.raises(DeviceError) as info:
        call(*args)  # type: ignore[operator]
    return info.value


# ---------------------------------------------------------------- the error itself


def test_a_device_error_carries_its_device_and_keeps_working_without_one() -> None:
    named = DeviceError("tracker: no answer", device="tracker")
    assert (str(named), named.device) == ("tracker: no answer", "tracker")
    assert DeviceError("old raise site").device is None
    target = NoTargetError("rig: no set measured the target", device="rig")
    assert isinstance(target, UserError) and target.device == "rig"
    back = pickle.loads(pickle.dumps(BeamBrokenError("t1: beam broken", 40, device="t1")))
    assert (str(back), back.code, back.device) == ("t1: beam broken", 40, "t1")


def test_device_errors_names_only_what_names_nothing_and_device_of_finds_the_cause() -> None:
    with pytest.raises(DeviceError) as info, device_errors("robot"):
        raise DeviceError("nameless")
    assert info.value.device == "robot"
    with pytest.raises(DeviceError) as info, device_errors("robot"):
        raise DeviceError("the tracker's", device="tracker")
    assert info.value.device == "tracker"
    try:
        try:
            raise DeviceError("t1: beam broken", device="t1")
        except DeviceError as exc:
            raise CampaignError(f"{exc}; campaign 3 is resumable") from exc
    except CampaignError as wrapped:
        assert device_of(wrapped) == "t1"
    assert device_of(CampaignError("the plan changed")) is None


# ---------------------------------------------------------------- robots


@pytest.fixture
def modbus_twin() -> Iterator[ModbusRobotTwin]:
    sim = ModbusRobotTwin(q0_deg=HOME_DEG)
    sim.start("127.0.0.181", 0)  # returns once listening
    try:
        yield sim
    finally:
        sim.stop()


def test_modbus_errors_name_the_robot_and_its_description_is_where_it_is(modbus_twin) -> None:
    host, port = modbus_twin.address
    robot = ModbusRobot(host, port, timeout_s=5.0, heartbeat_timeout_s=2.0)
    robot.connect()
    try:
        assert robot.describe() == DeviceDescription(ROBOT_NAME, "modbus", f"{host}:{port}")
        modbus_twin.faults = ModbusRobotFaults(estop=True)
        error = _raised(robot.move_joints, np.radians(HOME_DEG) + 0.05, 0.25)
        assert error.device == "robot"
        assert str(error).startswith(f"modbus-robot at {host}:{port}: e-stop"), str(error)
    finally:
        robot.close()
    # nothing listening: refused at connect, the robot named all the same
    nobody = ModbusRobot("127.0.0.182", port, heartbeat_timeout_s=1.0)
    error = _raised(nobody.connect)
    assert error.device == "robot" and "cannot connect" in str(error)


@pytest.mark.timeout(90)
def test_ur_errors_name_the_robot_and_its_dashboard_describes_it() -> None:
    pytest.importorskip("rtde_control")
    from cellcal.mocks.simulated_cell import SimulatedCell
    from cellcal.mocks.ur.dashboard import ROBOT_MODEL, SOFTWARE_VERSION
    from cellcal.mocks.ur.server import CellInURUnits, URTwin

    config = _ur10e_config()
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed=1)
    q0 = np.radians(config.robot.home_deg)
    sim = URTwin(CellInURUnits(cell), q0=q0, serial_number="20235500123")
    sim.start("127.0.0.183")  # returns once its three ports listen
    robot = URRobot("127.0.0.183", timeout_s=20.0)
    try:
        # asked of the dashboard, before or after ur_rtde connects
        assert robot.describe() == DeviceDescription(
            "robot", "ur", "127.0.0.183", "Universal Robots", ROBOT_MODEL, SOFTWARE_VERSION,
            "20235500123",
        )  # fmt: skip
        assert _raised(robot.actual_joints).device == "robot"  # not connected yet
        robot.connect()
        sim.inject_protective_stop()
        error = _raised(robot.move_joints, q0 + 0.05, 0.25)
        assert error.device == "robot" and "protective stop" in str(error)
        assert str(error).startswith("ur-robot at 127.0.0.183: "), str(error)
    finally:
        robot.close()
        sim.stop()
    # a dashboard that is not there: the description keeps only what the driver knows
    gone = URRobot("127.0.0.184", timeout_s=2.0)
    assert gone.describe() == DeviceDescription("robot", "ur", "127.0.0.184")
    error = _raised(gone.connect)
    assert error.device == "robot" and "cannot reach port 29999" in str(error)


def _ur10e_config():  # type: ignore[no-untyped-def]
    from cellcal.config import load_config

    ref = resources.files("cellcal") / "data" / "mock-cell-ur10e.toml"
    with resources.as_file(ref) as path:
        return load_config(path, relative_paths=False)


def test_the_simulated_robot_and_the_safety_gate_name_the_robot() -> None:
    from cellcal.config import load_config
    from cellcal.mocks.simulated_cell import SimulatedCell

    with resources.as_file(resources.files("cellcal") / "data" / "mock-cell.toml") as path:
        config = load_config(path, relative_paths=False)
    model = load_model(config.robot.model).model
    from_options = SimulatedRobot.from_options
    error = _raised(from_options, config.robot, DeviceContext(SimulatedClock()))
    assert error.device == "robot" and "needs --mock" in str(error)
    cell = SimulatedCell(config, model, seed=1)
    robot = SimulatedRobot(cell, SimulatedClock())
    assert robot.describe() == DeviceDescription("robot", "simulated")
    lo, _ = model.limits
    outside = np.radians(HOME_DEG)
    outside[0] = lo[0] - 0.1
    assert _raised(robot.move_joints, outside, 0.25).device == "robot"
    big = np.array([1e5, 1e5, 1e5])
    gate = GuardedRobot(robot, model, np.zeros(3), -big, big, 0.5)
    assert gate.describe() == robot.describe()
    refused = _raised(gate.move_joints, outside, 0.25)
    assert isinstance(refused, SafetyError) and refused.device == "robot"
    assert refused.at_pose(4).device == "robot"
    assert str(refused.at_pose(4)) == f"pose 4: {refused}"


# ---------------------------------------------------------------- the tracker


def _scripted(pairs: list, name: str = "t1", **kw: object) -> tuple[LineTracker, ScriptedTransport]:
    t = ScriptedTransport([IDN, ("INIT", ["OK"]), *pairs], drop_at=kw.pop("drop_at", None))
    lt = LineTracker(name, "scripted://", transport=t, timeout=0.2, backoff_s=0.0, **kw)  # type: ignore[arg-type]
    return lt, t


def test_tracker_errors_name_the_sensor_its_own_and_its_links() -> None:
    lt, _ = _scripted([("STAT?", ["ERR 4 UNKNOWN_COMMAND"])])
    lt.connect()
    error = _raised(lt.status)
    assert isinstance(error, TrackerError) and error.device == "t1"
    assert str(error) == "tracker t1: 'STAT?' answered ERR 4 UNKNOWN_COMMAND"
    # a broken beam: no target, the pose kept without the tracker
    lt, _ = _scripted([("MEAS 3 10", ["ERR 40 BEAM_BROKEN"])], beam_retries=0)
    lt.connect()
    error = _raised(lt.measure, 3, 10.0)
    assert isinstance(error, NoTargetError) and error.device == "t1"
    # the link drops and does not come back: the transport's own error, named
    lt, _ = _scripted([], reconnects=0, drop_at=3)
    lt.connect()
    error = _raised(lt.measure, 3, 10.0)
    assert isinstance(error, TransportError) and error.device == "t1"
    assert str(error) == "scripted: link dropped"


def test_an_unreachable_tracker_is_named_at_connect() -> None:
    lt = LineTracker("t2", "socket://127.0.0.185:9", timeout=0.5, reconnects=0, backoff_s=0.0)
    error = _raised(lt.connect)
    assert isinstance(error, TransportError) and error.device == "t2"
    assert "unreachable after 1 attempts" in str(error)


class StillTarget:
    """A target that stays where it is."""

    def sample(self, n: int) -> np.ndarray:
        return np.tile([1000.0, 200.0, 300.0], (n, 1))


@pytest.fixture
def tracker_twin() -> Iterator[tuple[str, int]]:
    server = TrackerTwin(StillTarget(), serial="SN-4711")
    try:
        yield server.start_tcp("127.0.0.186", 0)  # returns once listening
    finally:
        server.stop()


def test_the_tracker_describes_what_its_idn_answered(tracker_twin) -> None:
    host, port = tracker_twin
    lt = LineTracker("t1", f"socket://{host}:{port}", timeout=5.0)
    assert lt.describe() == DeviceDescription(
        "t1", "laser-tracker/line-protocol", f"socket://{host}:{port}"
    )  # not connected: nothing asked, nothing known
    lt.connect()
    try:
        assert lt.describe() == DeviceDescription(
            "t1", "laser-tracker/line-protocol", f"socket://{host}:{port}", MAKER, MODEL,
            FIRMWARE, "SN-4711",
        )  # fmt: skip
        assert f"{MAKER} {MODEL}, serial SN-4711" in lt.summary()  # the report's line
    finally:
        lt.close()


# ---------------------------------------------------------------- the camera rig


def _bundled(name: str) -> Path:
    with resources.as_file(resources.files("cellcal") / "data" / name) as path:
        return Path(path)


@pytest.fixture(scope="module")
def rig_and_target() -> tuple[Rig, Target]:
    return read_rig(_bundled("mock-rig.toml")), read_target(_bundled("mock-target.toml"))


def _files_rig(folder: Path, sets: int, rig: Rig) -> FilesRig:
    """``sets`` recorded sets of shading: no marker in any image."""
    folder.mkdir(parents=True)
    for k in range(sets):
        (folder / f"{k:03d}").mkdir()
        for cam in rig.cameras:
            ramp = np.add.outer(np.arange(cam.height), np.arange(cam.width)) % 200
            write_image(folder / f"{k:03d}" / f"{cam.name}.png", ramp.astype(np.uint8))
    cameras = [{"name": c.name} for c in rig.cameras]
    options = FilesRigOptions.model_validate({"directory": str(folder), "cameras": cameras})
    return FilesRig(options)


def test_rig_errors_name_the_sensor_not_the_capture(tmp_path, rig_and_target) -> None:
    rig, target = rig_and_target
    clock = SimulatedClock()
    # the capture calls itself "rig"; the sensor is "probe" in the configuration
    missing = CameraRigSensor("probe", _files_rig(tmp_path / "a", 0, rig), rig, target, clock)
    error = _raised(missing.connect)
    assert error.device == "probe" and str(error).startswith("rig rig: no image sets in ")
    blind = CameraRigSensor("probe", _files_rig(tmp_path / "b", 3, rig), rig, target, clock)
    blind.connect()
    error = _raised(blind.measure, 2, 10.0)
    assert isinstance(error, NoTargetError) and error.device == "probe"
    one = CameraRigSensor("probe", _files_rig(tmp_path / "c", 1, rig), rig, target, clock)
    one.connect()
    error = _raised(one.measure, 2, 10.0)  # the recording ends after its one set
    assert error.device == "probe" and str(error).startswith("no more image sets in ")
    for sensor in (missing, blind, one):
        sensor.close()
    two = Rig(rig.name, rig.cameras[:2])  # a rig file of other cameras than the capture's
    with pytest.raises(DeviceError) as info:
        CameraRigSensor("probe", _files_rig(tmp_path / "d", 0, rig), two, target, clock)
    assert info.value.device == "probe" and "are not the rig file's" in str(info.value)


def test_a_rig_of_recorded_sets_describes_its_cameras_by_name(tmp_path, rig_and_target) -> None:
    rig, target = rig_and_target
    folder = tmp_path / "recording"
    cameras = _files_rig(folder, 1, rig)
    sensor = CameraRigSensor("probe", cameras, rig, target, SimulatedClock(), address=str(folder))
    assert sensor.describe() == DeviceDescription(
        "probe",
        "photogrammetry/cameras",
        str(folder),
        parts=tuple(DeviceDescription(c.name, "files", f"{c.name}.png") for c in rig.cameras),
    )


def test_aravis_cameras_describe_themselves_over_gige_vision() -> None:
    from cellcal.drivers.cameras.aravis import AravisRig, AravisRigOptions, aravis_missing
    from cellcal.mocks import netns
    from cellcal.mocks.rig.gige_cameras import GigECameraTwin

    if reason := aravis_missing():
        pytest.skip(reason)
    grey = np.full((48, 64), 90, dtype=np.uint8)
    twin = GigECameraTwin(
        ["left", "right"], lambda name: grey, width=64, height=48, first_address=187
    )
    try:
        twin.start()  # returns once the cameras answer
    except netns.NamespaceUnavailableError as exc:
        pytest.skip(str(exc))
    cams = [{"name": n, "address": a} for n, a in twin.addresses.items()]
    options = AravisRigOptions.model_validate({"cameras": cams, "netns": twin.netns})
    rig = AravisRig(options)
    try:
        assert rig.describe() == (
            DeviceDescription("left", "aravis", "127.0.0.187"),
            DeviceDescription("right", "aravis", "127.0.0.188"),
        )  # not connected: the configuration's names and addresses only
        rig.connect()
        left, right = rig.describe()
    finally:
        rig.close()
        twin.stop()
    # Aravis's fake camera: its vendor, model, serial (the twin's), and its device
    # version for the firmware (it has no DeviceFirmwareVersion)
    assert (left.device, left.address, left.maker, left.model) == (
        "left", "127.0.0.187", "Aravis", "Fake"
    )  # fmt: skip
    assert (left.serial, right.serial) == ("SIM-left", "SIM-right")
    assert left.firmware and left.firmware[0].isdigit(), left.firmware
