"""A tracker that takes long to get ready says what it is doing, and the service shows
it (issue 31: the sensor not warmed up is waited for "with the tracker's own state in
the status"): the emScon driver's warm-up and initialisation reach the device's line of
the service's status through ``DeviceContext.report`` while the engine thread connects."""

from __future__ import annotations

import threading
import tomllib
from pathlib import Path

import pytest

from cellcal.clock import SimulatedClock
from cellcal.config import config_from_dict
from cellcal.files.models import load_model
from cellcal.service.control import CONNECTING, READY, Control
from cellcal.service.worker import Worker, device_names

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60)]

ROOT = Path(__file__).resolve().parents[2]


def test_the_status_shows_the_tracker_warming_up(tmp_path: Path):
    cell = tomllib.loads((ROOT / "config" / "mock-cell-emscon.toml").read_text())
    cell["simulation"]["faults"] = {"tracker_warmup_s": 2.5}
    config = config_from_dict(cell)
    seen: list[str] = []
    control = Control(device_names(config), lambda kind, data: None)
    nominal = load_model(config.robot.model).model
    worker = Worker(
        control, config, nominal, str(tmp_path / "c.db"), SimulatedClock(0.0), mock=True
    )
    set_device = control.set_device

    def recorded(name: str, state: str, message: str = "") -> None:
        if name == "tracker" and state == CONNECTING and message:
            seen.append(message)
        set_device(name, state, message)

    control.set_device = recorded  # type: ignore[method-assign]
    connected: list[bool] = []
    thread = threading.Thread(target=lambda: connected.append(worker._connect()))
    thread.start()
    try:
        thread.join(45)
    finally:
        worker._disconnect()
    assert connected == [True]
    assert any("laser warming up (heating up); waited" in m for m in seen), seen
    assert any(m.startswith("initialising (up to") for m in seen), seen
    assert control.devices["tracker"] == {"state": READY, "message": ""}
