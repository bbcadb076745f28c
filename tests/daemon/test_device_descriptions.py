"""The campaign's side of "facts, not text": every DeviceError that reaches the engine or
the device factory names its device (a driver's own, or named there when a device below
did not); and a campaign records what its devices are — one ``device`` event per device
at each start and resume, the JSON of its description — beside the line the report
shows. The twins of the mock campaigns listen on 127.0.0.191–127.0.0.194 (their hosts
moved there for these tests; the cameras' are inside a namespace of their own)."""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.campaign.devices import build_devices
from cellcal.campaign.records import CampaignEvent, PoseStored
from cellcal.campaign.runner import resume_campaign, start_campaign
from cellcal.clock import SimulatedClock
from cellcal.config import CellConfig, config_from_dict, with_robot
from cellcal.drivers.base import DeviceDescription
from cellcal.errors import CampaignError, DeviceError, NoTargetError, device_of
from cellcal.families import find
from cellcal.files.models import load_model
from cellcal.mocks.modbus import server as modbus_robot_server
from cellcal.mocks.tracker import server as tracker_server
from cellcal.mocks.tracker.server import FIRMWARE, MAKER, MODEL, TrackerTwin
from cellcal.store.database import Store
from cellcal.store.devices import (
    DEVICE_EVENT,
    description_of,
    device_message,
    stored_descriptions,
)
from tests.conftest import tracker_cell
from tests.daemon.stand_ins import Robot, Sensor, acquire_at
from tests.drivers.families import cell_for

Q = np.radians([0.0, -30.0, 40.0, 0.0, -20.0, 0.0])

# ---------------------------------------------------------------- the engine


def _arm(fault: DeviceError | None = None, off: float = 0.0) -> Robot:
    """Goes where it is sent, or raises ``fault`` (a DeviceError that names nothing)."""
    return Robot(Q, off, fault, name="arm-7")


def _acquire(robot: Robot, *sensors: Sensor) -> tuple[BaseException | None, list[CampaignEvent]]:
    return acquire_at(robot, list(sensors), Q)


@pytest.mark.timeout(30)
def test_every_device_error_leaving_the_engine_names_its_device() -> None:
    error, events = _acquire(_arm(DeviceError("arm-7: protective stop")), Sensor("t1"))
    assert error is not None and error.device == "robot"
    assert str(error) == "arm-7: protective stop"  # the message as it was
    assert [e.kind for e in events] == ["device-error"]
    error, _ = _acquire(_arm(off=0.01), Sensor("t1"))
    assert error is not None and error.device == "robot"
    assert str(error).startswith("pose 0: arm-7: reports ")
    error, events = _acquire(_arm(), Sensor("t1"), Sensor("rig", DeviceError("rig: no frame")))
    assert error is not None and error.device == "rig" and str(error) == "rig: no frame"
    assert [e.kind for e in events] == ["sensor-retry", "sensor-retry", "device-error"]
    # a sensor that does not see its target is left out of the pose, not a fault
    error, events = _acquire(_arm(), Sensor("t1"), Sensor("rig", NoTargetError("rig: nothing")))
    assert error is None and [e.kind for e in events] == ["no-target"]


# ---------------------------------------------------------------- the device factory


@pytest.fixture
def tracker_twin() -> Iterator[tuple[str, int]]:
    server = TrackerTwin(_Still())
    try:
        yield server.start_tcp("127.0.0.191", 0)  # returns once listening
    finally:
        server.stop()


class _Still:
    def sample(self, n: int) -> np.ndarray:
        return np.tile([1500.0, 0.0, 500.0], (n, 1))


def _real_cell(robot_address: str, tracker_address: str) -> CellConfig:
    return config_from_dict(
        {
            "robot": {"driver": "modbus", "address": robot_address, "heartbeat_timeout_s": 1.0},
            "sensor": [
                {
                    "name": "t1",
                    "kind": "laser-tracker",
                    "address": tracker_address,
                    "reference": True,
                    "reconnects": 0,
                    "timeout_s": 2.0,
                }
            ],
        },
        "cell",
    )


@pytest.mark.timeout(60)
def test_devices_that_do_not_connect_are_named(tracker_twin) -> None:
    host, port = tracker_twin
    nominal = load_model("kuka-kr5-arc").model
    clock = SimulatedClock()
    # the tracker is not where the configuration says: the sensor is named
    config = _real_cell("127.0.0.192:1502", "socket://127.0.0.192:9")
    with pytest.raises(DeviceError) as info:
        build_devices(config, nominal, clock, mock=False, seed=None)
    assert info.value.device == "t1" and "unreachable" in str(info.value)
    # the tracker answers, the robot's controller does not: the robot is named
    config = _real_cell("127.0.0.192:1502", f"socket://{host}:{port}")
    with pytest.raises(DeviceError) as info:
        build_devices(config, nominal, clock, mock=False, seed=None)
    assert info.value.device == "robot" and "cannot connect" in str(info.value)
    # a family that needs --mock, at build
    simulated = config_from_dict(
        {"sensor": [{"name": "t1", "kind": "laser-tracker", "reference": True}]}
    )
    with pytest.raises(DeviceError, match="needs --mock") as info:
        build_devices(simulated, nominal, clock, mock=False, seed=None)
    assert info.value.device == "robot"


@pytest.mark.timeout(60)
def test_a_campaign_that_fails_on_a_device_says_which(tmp_path, monkeypatch, twin_hosts) -> None:
    """What the service reads to mark the device at fault: the campaign's error, whose
    cause names the device."""
    from cellcal.mocks import simulated_devices

    def stopped(self: Any, q: np.ndarray, speed: float) -> None:
        raise DeviceError("simulated-robot: protective stop")

    monkeypatch.setattr(simulated_devices.SimulatedRobot, "move_joints", stopped)
    config = with_robot(_small(tracker_cell()), driver="simulated")
    with pytest.raises(CampaignError, match="protective stop") as info:
        start_campaign(config, str(tmp_path / "c.db"), config_path=None, mock=True)
    assert device_of(info.value) == "robot"


# ---------------------------------------------------------------- what a campaign records


@pytest.fixture
def twin_hosts(monkeypatch) -> None:
    """The mock campaigns' twins on this file's addresses."""
    monkeypatch.setattr(tracker_server, "TRACKER_HOST", "127.0.0.193")
    monkeypatch.setattr(modbus_robot_server, "MODBUS_HOST", "127.0.0.194")


def _small(config: CellConfig, samples: int = 4) -> CellConfig:
    data = config.model_dump()
    data["campaign"].update(
        grid=[2, 2, 3], validation_inside=2, validation_per_region=1, samples_per_pose=samples
    )
    return config_from_dict(data, "small cell")


def _device_events(db: Path) -> list[str]:
    with sqlite3.connect(db) as conn:
        rows = conn.execute("SELECT message FROM events WHERE kind = 'device' ORDER BY id")
        return [m for (m,) in rows]


@pytest.mark.twin
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_mock_campaign_records_its_devices_and_a_resume_records_them_again(
    tmp_path, twin_hosts
) -> None:
    db = tmp_path / "c.db"
    stop = threading.Event()

    def stop_after_2(record: object) -> None:
        if isinstance(record, PoseStored) and record.done == 2:
            stop.set()

    config = _small(tracker_cell())
    out = start_campaign(
        config, str(db), config_path=None, mock=True, stop=stop, subscribers=[stop_after_2]
    )
    assert out.acquisition.interrupted
    first = _device_events(db)
    robot, tracker = (description_of(m) for m in first if m.startswith("{"))
    assert robot is not None and tracker is not None
    assert (robot.device, robot.family, robot.maker) == ("robot", "modbus", None)
    assert robot.address is not None and robot.address.startswith("127.0.0.194:")
    assert tracker == DeviceDescription(
        "tracker", "laser-tracker/line-protocol", tracker.address, MAKER, MODEL, FIRMWARE,
        "SIM-0001",
    )  # fmt: skip
    assert tracker.address is not None and tracker.address.startswith("socket://127.0.0.193:")
    # the report's line of the tracker, as before
    assert any(m.startswith("tracker at socket://") and "serial SIM-0001" in m for m in first)
    resume_campaign(str(db), out.campaign_id)
    assert len(_device_events(db)) == 2 * len(first)  # once more, at the resume
    store = Store(db)
    try:
        latest = stored_descriptions(store, out.campaign_id)
    finally:
        store.close()
    assert [d.device for d in latest] == ["robot", "tracker"]
    assert latest[1].serial == "SIM-0001" and latest[1].address != tracker.address  # new twin
    with sqlite3.connect(db) as conn:
        serials = conn.execute(
            "SELECT json_extract(message, '$.serial') FROM events "
            "WHERE kind = 'device' AND json_valid(message) ORDER BY id"
        ).fetchall()
    assert serials == 2 * [(None,), ("SIM-0001",)]


@pytest.mark.twin
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_rig_campaign_records_each_camera_as_it_says_of_itself(tmp_path, twin_hosts) -> None:
    from cellcal.drivers.cameras.aravis import aravis_missing

    config = _small(cell_for(find("sensor", "photogrammetry", "cameras")), samples=2)
    out = start_campaign(config, str(tmp_path / "c.db"), config_path=None, mock=True, seed=7)
    store = Store(tmp_path / "c.db")
    try:
        devices = {d.device: d for d in stored_descriptions(store, out.campaign_id)}
    finally:
        store.close()
    assert list(devices) == ["robot", "tracker", "rig"]
    rig = devices["rig"]
    names = [c.name for c in config.sensor[-1].capture.cameras]  # type: ignore[attr-defined]
    assert rig.family == "photogrammetry/cameras" and [p.device for p in rig.parts] == names
    if aravis_missing() is None and rig.parts[0].family == "aravis":
        # GigE Vision twins (Aravis's fake cameras): what each camera said of itself
        assert {(p.maker, p.model) for p in rig.parts} == {("Aravis", "Fake")}
        assert [p.serial for p in rig.parts] == [f"SIM-{n}" for n in names]
    else:  # cameras rendered in-process: their names only
        assert {(p.family, p.address, p.serial) for p in rig.parts} == {("rendered", None, None)}


# ---------------------------------------------------------------- the records themselves


def test_a_description_goes_to_json_and_back_and_text_lines_are_no_description() -> None:
    rig = DeviceDescription(
        "rig",
        "photogrammetry/cameras",
        "192.168.10.21, 192.168.10.22",
        parts=(
            DeviceDescription("cam0", "aravis", "192.168.10.21", "Basler", "a2A1920", "1.2", "4"),
            DeviceDescription("cam1", "aravis", "192.168.10.22"),
        ),
    )
    message = device_message(rig)
    assert "\n" not in message and json.loads(message)["parts"][0]["maker"] == "Basler"
    assert description_of(message) == rig
    for text in (
        "tracker at socket://10.0.0.9:5555: Leica AT960, serial 1, firmware 2",
        "{not json",
        '{"device": "robot"}',  # no family
        "[1, 2]",
    ):
        assert description_of(text) is None, text


def test_the_latest_description_of_each_device_is_the_campaigns() -> None:
    class Events:
        def events(self, campaign_id: int) -> list[dict[str, Any]]:
            return [
                {"kind": DEVICE_EVENT, "message": m}
                for m in (
                    device_message(DeviceDescription("robot", "ur", "10.0.0.5", serial="1")),
                    "tracker at /dev/ttyUSB0: Leica AT960, serial 7, firmware 2.4",
                    device_message(DeviceDescription("tracker", "laser-tracker/line-protocol")),
                    device_message(DeviceDescription("robot", "ur", "10.0.0.5", serial="2")),
                )
            ] + [{"kind": "resumed", "message": '{"device": "x", "family": "y"}'}]

    latest = stored_descriptions(Events(), 1)
    assert [(d.device, d.serial) for d in latest] == [("robot", "2"), ("tracker", None)]
