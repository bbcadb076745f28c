"""yrcom (PyPI; an HSES client nobody here wrote, "verified live" on a YRC1000), unchanged,
against ``cellcal mock yaskawa-hses`` as a process (UDP on 127.0.0.57): the status bits,
the servo, a pulse move and the position it reaches, hold, the latest alarm and its
reset — and a refusal, which yrcom reports by the byte it reads as the status (the
answer's added-status size: yrcom reads the status one byte late, so only that it
failed is checked)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

yrcom = pytest.importorskip("yrcom")

pytestmark = [pytest.mark.twin, pytest.mark.timeout(90)]

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "mock-cell-yaskawa-hses.toml"
PPD = [1434.6, 1434.6, 1227.8, 807.6, 807.6, 474.2]  # the configuration's


@pytest.fixture
def controller(tmp_path: Path):
    twin = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "yaskawa-hses", "--listen", "127.0.0.57:0",
         "--config", str(CONFIG), "--time-scale", "0.01"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )  # fmt: skip
    assert twin.stdout is not None
    address = twin.stdout.readline().strip()  # printed once it listens
    assert address.startswith("127.0.0.57:"), twin.stderr.read() if twin.stderr else ""
    yield int(address.rpartition(":")[2])
    twin.send_signal(signal.SIGTERM)
    twin.communicate(timeout=30)
    assert twin.returncode == 0


def _wait_still(c: object) -> None:
    deadline = time.monotonic() + 20
    while c.read_status()["running"]:  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "still running"
        time.sleep(0.01)


def test_yrcom_reads_drives_and_resets_the_twin(controller: int):
    with yrcom.HsesClient("127.0.0.57", port=controller, timeout=5.0) as c:
        status = c.read_status()
        assert status["play"] and status["cmd_remote"] and not status["teach"]
        assert not status["servo_on"]  # a controller starts with the servo off
        home = c.read_position(1)
        assert [home[f"pos_{a}"] for a in "SLURBT"] == [
            round(d * p) for d, p in zip([0, -30, 40, 0, -20, 0], PPD, strict=True)
        ]
        # the servo off: the move is refused (yrcom's HsesError)
        goal = [round(d * p) for d, p in zip([10, -25, 35, 5, -15, 20], PPD, strict=True)]
        with pytest.raises(yrcom.HsesError):
            c.move_pulse(yrcom.PulseMove(robot_axes=goal, speed=5000))
        c.servo(True)
        assert c.read_status()["servo_on"]
        c.move_pulse(yrcom.PulseMove(robot_axes=goal, speed=5000))
        _wait_still(c)
        now = c.read_position(1)
        assert [now[f"pos_{a}"] for a in "SLURBT"] == goal
        # beyond axis 1's limit (±155°): the controller stops with an alarm
        far = [round(170 * PPD[0]), *goal[1:]]
        c.move_pulse(yrcom.PulseMove(robot_axes=far, speed=5000))
        _wait_still(c)
        assert c.read_status()["alarm"]
        alarm = c.read_alarm(1)
        assert alarm["alarm_code"] == 4101 and "LIMIT AXIS 1" in alarm["alarm_name"]
        c.reset_alarm()
        assert not c.read_status()["alarm"]
        c.hold(True)
        assert c.read_status()["hold_cmd"]
        c.hold(False)
        assert [c.read_position(1)[f"pos_{a}"] for a in "SLURBT"] == goal
