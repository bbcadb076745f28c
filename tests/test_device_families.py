"""The registry of device families, as a newcomer adding one uses it: a driver module
and a twin module (here both in this file), one line in the table, and the configuration,
the device factory and the contract suite take the new family up — nothing else
changes. Also: what the configuration refuses about a device section, and the
configuration of an earlier version stored with a campaign, brought up to date."""

from __future__ import annotations

import socket
import socketserver
import threading
from typing import Literal

import click
import numpy as np
import pytest

import cellcal.families as registry
from cellcal.campaign.devices import build_devices
from cellcal.clock import Clock, SimulatedClock
from cellcal.config import config_from_dict
from cellcal.config_earlier import upgrade_stored
from cellcal.device_options import SensorOptions
from cellcal.drivers.base import DeviceContext, Series, host_port, label
from cellcal.errors import ConfigError, DeviceError, InputError
from cellcal.families import Family
from cellcal.files.models import load_model
from cellcal.mocks.twins import RunningTwin
from tests.conftest import TRACKER_CELL
from tests.drivers import test_sensor_contract
from tests.drivers.families import bundled_cells, cell_for

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60)]

# ---------------------------------------------------------------- module 1: the driver


class EchoOptions(SensorOptions):
    """A made-up tracker dialect: one line "M" asks, "x y z" (mm) answers."""

    kind: Literal["laser-tracker"] = "laser-tracker"
    driver: Literal["echo"] = "echo"
    timeout_s: float = 2.0


class EchoTracker:
    def __init__(self, name: str, address: str, timeout_s: float, clock: Clock) -> None:
        self.name, self.address, self.timeout_s, self.clock = name, address, timeout_s, clock
        self.sock: socket.socket | None = None

    @classmethod
    def from_options(cls, options: EchoOptions, context: DeviceContext) -> EchoTracker:
        return cls(options.name, options.address, options.timeout_s, context.clock)

    def connect(self) -> None:
        try:
            self.sock = socket.create_connection(host_port(self.address, 7), self.timeout_s)
        except OSError as exc:
            raise DeviceError(f"{label(self.name, self.address)}: {exc.strerror}") from None
        self.lines = self.sock.makefile("rw", newline="\n")

    def measure(self, n: int, rate_hz: float) -> Series:
        t0 = self.clock.now()
        xyz = []
        for _ in range(n):
            self.lines.write("M\n")
            self.lines.flush()
            xyz.append([float(v) for v in self.lines.readline().split()])
        self.clock.sleep(n / rate_hz)
        t = t0 + np.arange(n) / rate_hz
        return Series(self.name, t, t + 1.0, np.array(xyz))

    def close(self) -> None:
        if self.sock is not None:
            self.lines.close()
            self.sock.close()
            self.sock = None


# ---------------------------------------------------------------- module 2: the twin


def serve(options: EchoOptions, cell, time_scale: float) -> RunningTwin:
    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            for line in self.rfile:
                if line.strip() == b"M":
                    p = cell.sample(options.name, 1)[0]
                    self.wfile.write(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}\n".encode())

    server = socketserver.ThreadingTCPServer(("127.0.0.81", 0), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()

    class Stoppable:
        def stop(self) -> None:
            server.shutdown()
            server.server_close()

    host, port = server.server_address[:2]
    return RunningTwin(options.model_copy(update={"address": f"{host}:{port}"}), Stoppable())


# ---------------------------------------------------------------- the table line

ECHO = Family(
    "sensor",
    "laser-tracker",
    "echo",
    f"{__name__}:EchoOptions",
    f"{__name__}:EchoTracker",
    f"{__name__}:serve",
    "a made-up tracker dialect",
)


@pytest.fixture
def echo_family(monkeypatch):
    monkeypatch.setattr(registry, "FAMILIES", (*registry.FAMILIES, ECHO))
    return ECHO


def _with_sensor(**sensor: object):
    data = bundled_cells()[0].model_dump()
    data["sensor"] = [*data["sensor"], {"name": "echo1", "kind": "laser-tracker", **sensor}]
    return data


def test_a_family_added_to_the_table_is_configured_built_and_contract_tested(echo_family):
    config = config_from_dict(_with_sensor(driver="echo", address="10.0.0.9:7"))
    assert type(config.sensor[-1]).__name__ == "EchoOptions"
    with pytest.raises(ConfigError, match=r"sensor\.2\.beam_retries: unknown key"):
        config_from_dict(_with_sensor(driver="echo", beam_retries=3))
    # The contract suite runs on it like on every other family.
    test_sensor_contract.test_contract(echo_family)
    # Mock mode: the twin, and the same driver pointed at it.
    nominal = load_model(config.robot.model).model
    devices = build_devices(config, nominal, SimulatedClock(), mock=True, seed=1)
    try:
        echo = devices.sensors[-1].sensor
        assert isinstance(echo, EchoTracker) and echo.address.startswith("127.0.0.81:")
        np.testing.assert_allclose(
            echo.measure(2, 10.0).mean, devices.simulated_cell.true_position("echo1"), atol=0.1
        )
    finally:
        devices.close()
    assert cell_for(echo_family).sensor[-1].driver == "echo"


def test_a_family_added_to_the_table_has_its_cellcal_mock_command(echo_family):
    """A line without a command of its own gets the one made from it: its twin, served
    for the configuration's device of the family."""
    from click.testing import CliRunner

    from cellcal.commands.mock import mock

    result = CliRunner().invoke(mock, ["--help"])
    assert result.exit_code == 0
    assert "echo" in result.output.partition("Commands:")[2].split()
    result = CliRunner().invoke(mock, ["echo", "--help"])
    assert result.exit_code == 0, result.output
    for option in ("--config", "--sensor", "--seed", "--time-scale"):
        assert option in result.output
    result = CliRunner().invoke(mock, ["echo"])
    assert result.exit_code == 2 and "Missing option '--config'" in result.output
    # the configuration's device of the family is served, and there is none in this one
    cell = str(TRACKER_CELL)
    result = CliRunner().invoke(mock, ["echo", "--config", cell])
    assert isinstance(result.exception, InputError)
    assert str(result.exception) == f"no laser-tracker/echo sensor in {cell} (its: none)"
    robot = Family("robot", "robot", "echo-arm", "x:O", "x:R", "x:serve", "an arm")
    with pytest.MonkeyPatch.context() as m:
        m.setattr(registry, "FAMILIES", (*registry.FAMILIES, robot))
        result = CliRunner().invoke(mock, ["echo-arm", "--config", cell])
    assert str(result.exception) == f"{cell}: the robot has driver = 'modbus', not 'echo-arm'"


def test_the_table_is_consistent():
    tags = [f.tag for f in registry.FAMILIES]
    assert len(set(tags)) == len(tags)
    names = [f.mock_name for f in registry.FAMILIES if f.mock_name is not None]
    assert sorted(set(names)) == [
        "abb-rws",
        "cameras",
        "fanuc-rmi",
        "kuka-eki",
        "kuka-kvp",
        "modbus-robot",
        "tracker",
        "ur",
        "yaskawa-hses",
    ]
    # two dialects of one kind share their command (cellcal mock tracker --dialect)
    for name in set(names):
        commands = {f.mock_command for f in registry.FAMILIES if f.mock_name == name}
        assert len(commands) == 1 and None not in commands
    for f in registry.FAMILIES:
        options = f.options_model()
        assert options.model_fields["driver"].default == f.driver
        if f.role == "sensor":
            assert options.model_fields["kind"].default == f.kind
        assert hasattr(f.device_class(), "from_options")
        assert (f.twin is None) == f.mock_only
        if f.twin is not None:
            assert callable(registry.load(f.twin))
        if f.mock_command is not None:
            assert isinstance(registry.load(f.mock_command), click.Command)
        assert f.simulated_as == ("images" if f.kind == "photogrammetry" else "point")


def test_the_camera_backends_are_rows_of_the_registry():
    """Each backend's options, rig class and twin load from its row; the backends a
    configuration may name are the table's, and those ``[sensor.capture]`` takes."""

    from cellcal.drivers.cameras.backends import BACKENDS, rig_class
    from cellcal.drivers.photogrammetry import CameraRigOptions

    for b in registry.CAMERA_BACKENDS:
        assert registry.load(b.options).model_fields["backend"].default == b.name
        assert rig_class(b.name) is registry.load(b.rig)
        assert hasattr(rig_class(b.name), "from_options")
        assert b.twin is None or callable(registry.load(b.twin))
        assert b.unavailable is None or callable(registry.load(b.unavailable))
    # [sensor.capture] takes exactly the backends a configuration may name
    assert tuple(b.name for b in registry.camera_backends(configurable=True)) == BACKENDS
    for name in BACKENDS:
        camera = {"name": "c0", "address": "10.0.0.21"}
        capture = {"backend": name, "cameras": [camera], "directory": "sets"}
        if name != "files":
            capture.pop("directory")
        sensor = {"name": "rig", "rig_file": "r", "target_file": "t", "capture": capture}
        assert CameraRigOptions.model_validate(sensor).capture.backend == name
    assert "rendered" not in BACKENDS and rig_class("rendered").__name__ == "RenderedRig"
    with pytest.raises(KeyError):
        rig_class("gstreamer")


@pytest.mark.parametrize(
    ("robot", "message"),
    [
        ({"driver": "fanuc"}, r"robot\.driver: no robot driver 'fanuc' \(choose simulated, modbus, ur, kuka-kvp, kuka-eki, abb-rws, fanuc-rmi, yaskawa-hses\)"),  # noqa: E501
        ({"driver": "ur", "map": {}}, r"robot\.map: unknown key"),
        ({"driver": "ur", "heartbeat_timeout_s": 1.0}, r"robot\.heartbeat_timeout_s: unknown key"),
        ({"driver": "simulated", "move_timeout_s": 5.0}, r"robot\.move_timeout_s: unknown key"),
        ({"driver": "modbus", "modbus": 5}, r"robot\.modbus: unknown key \(renamed: map"),
        ({"driver": "modbus", "modbus": {}, "map": {}}, r"\[robot\.modbus\] is deprecated and \[robot\.map\] replaces it; both are given"),  # noqa: E501
        ({"driver": "ur", "settle_timeout_s": 9.0, "move_timeout_s": 9.0}, r"robot\.settle_timeout_s is deprecated and robot\.move_timeout_s replaces it"),  # noqa: E501
        ({"driver": "modbus", "map": {"status": 12}}, r"robot\.map: actual_joints .* and status .* overlap"),  # noqa: E501
        ({"driver": "modbus", "map": {"sequence": 7}}, r"robot\.map: sequence \(7\) must be the register after command"),  # noqa: E501
        ({"driver": "modbus", "map": {"speed": 65535}}, r"robot\.map: speed \(2 registers at 65535\) runs past 65535"),  # noqa: E501
        ({"driver": "modbus", "map": {"device_id": 256}}, r"robot\.map\.device_id: "),
    ],
)  # fmt: skip
def test_robot_options_that_do_not_belong_to_the_driver_are_refused(robot, message):
    data = bundled_cells()[0].model_dump()
    data["robot"] = {"model": "kuka-kr5-arc", **robot}
    with pytest.raises(ConfigError, match=message):
        config_from_dict(data)


@pytest.mark.parametrize(
    ("sensor", "message"),
    [
        ({"kind": "laser-tracker", "url": "socket://h:1", "address": "socket://h:1"}, r"sensor\.2\.url is deprecated and sensor\.2\.address replaces it; both are given"),  # noqa: E501
        ({"kind": "laser-tracker", "driver": "nmea"}, r"sensor\.2\.driver: no laser-tracker driver 'nmea' \(choose line-protocol, emscon\)"),  # noqa: E501
        ({"kind": "photogrammetry", "driver": "simulated"}, r"sensor\.2\.driver = \"simulated\" was the noise model of an earlier cellcal"),  # noqa: E501
        ({"kind": "sonar"}, r"sensor\.2\.kind: 'sonar' is not a sensor kind \(laser-tracker, photogrammetry\)"),  # noqa: E501
        ({"driver": "line-protocol"}, r"sensor\.2\.kind: required key missing"),
        ({"kind": "photogrammetry", "timeout_s": 3.0}, r"sensor\.2\.rig_file: required key missing"),  # noqa: E501
        ({"kind": "photogrammetry", "rig_file": "r", "target_file": "t", "capture": {"backend": "files", "directory": "d", "cameras": [{"name": "c"}]}, "timeout_s": 3.0}, r"sensor\.2\.timeout_s: unknown key"),  # noqa: E501
        ({"kind": "photogrammetry", "rig_file": "r", "target_file": "t", "capture": {"backend": "rendered", "cameras": ["c"], "scene": 1}}, r"sensor\.2\.capture: backend: 'rendered' is not a camera backend \(choose aravis, opencv, files\)"),  # noqa: E501
        ({"kind": "laser-tracker", "reflector": "RRR99"}, r"sensor\.2\.reflector: "),
    ],
)  # fmt: skip
def test_sensor_options_that_do_not_belong_to_the_driver_are_refused(sensor, message):
    data = bundled_cells()[0].model_dump()
    data["sensor"] = [*data["sensor"], {"name": "extra", **sensor}]
    with pytest.raises(ConfigError, match=message):
        config_from_dict(data)


def test_a_driver_means_the_same_in_real_mode_and_refuses_what_it_cannot_reach():
    config = bundled_cells()[0]
    nominal = load_model(config.robot.model).model
    with pytest.raises(
        DeviceError,
        match=r"robot\.address is empty: where is the controller \(driver = \"modbus\"\)",
    ):
        build_devices(config, nominal, SimulatedClock(), mock=False, seed=None)
    data = config.model_dump()
    data["robot"]["address"] = "127.0.0.1:9"
    rig = data["sensor"][1] | {"reference": True, "rig_file": "/no/such/rig.toml"}
    with pytest.raises(DeviceError, match=r"sensor rig: .*/no/such/rig\.toml"):
        build_devices(
            config_from_dict({**data, "sensor": [rig]}),
            nominal,
            SimulatedClock(),
            mock=False,
            seed=None,
        )


def test_a_configuration_stored_by_an_earlier_version_is_brought_up_to_date():
    old = {
        "name": "old",
        "robot": {
            "model": "kuka-kr5-arc",
            "driver": "modbus",
            "address": "10.1.1.1",
            "settle_timeout_s": 60.0,
            "modbus": {"port": 1502, "device_id": 3, "word_order": "little", "error": 2,
                       "timeout_s": 45.0, "heartbeat": 0, "status": 1, "ack": 3},
        },
        "sensor": [
            {"name": "tracker", "kind": "laser-tracker", "driver": "simulated", "url": "",
             "reference": True},
        ],
        "simulation": {"rig_noise_mm": 0.05},
    }  # fmt: skip
    config = config_from_dict(upgrade_stored(old))
    assert config.robot.address == "10.1.1.1:1502" and config.robot.move_timeout_s == 45.0
    assert config.robot.map.device_id == 3 and config.robot.map.word_order == "little"
    assert [s.driver for s in config.sensor] == ["line-protocol"]
    # the rig's noise model is gone: its campaigns cannot be resumed, and say why
    rig = {"name": "rig", "kind": "photogrammetry", "driver": "simulated", "url": ""}
    with pytest.raises(ConfigError, match=r"sensor rig: .*noise model.* cannot be resumed"):
        upgrade_stored({**old, "sensor": [*old["sensor"], rig]})
    old["robot"] = {"model": "ur10e", "driver": "ur", "settle_timeout_s": 30.0, "modbus": {}}
    assert config_from_dict(upgrade_stored(old)).robot.move_timeout_s == 30.0
