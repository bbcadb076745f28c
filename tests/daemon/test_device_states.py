"""Each device's state in the service: a tracker that is not there yet is ``fault`` with
the driver's one line while the robot waits ``connecting``; the service tries again
with backoff and, once the tracker answers, every device is ``ready`` — nothing
restarted by hand. And which device an error names."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call
from cellcal.config import config_from_dict
from cellcal.service.worker import faulty_device
from tests.e2e import test_standalone_twins as standalone

TRACKER = ("127.0.0.77", 5555)
ROBOT = ("127.0.0.78", 1502)
CONFIG = standalone.config_on(TRACKER, ROBOT)

pytestmark = [pytest.mark.twin, pytest.mark.timeout(180)]


def test_which_device_an_error_names() -> None:
    import tomllib

    config = config_from_dict(tomllib.loads(CONFIG), "cell")
    assert faulty_device(config, "sensor tracker: no answer") == "tracker"
    assert faulty_device(config, "tracker: beam broken") == "tracker"
    assert faulty_device(config, "tracker at socket://10.0.0.9:5555: unreachable") == "tracker"
    assert faulty_device(config, "modbus-robot at 10.0.0.5:502: e-stop during the move") == (
        "robot"
    )
    assert faulty_device(config, "robot.move: timed out") == "robot"
    assert faulty_device(config, "the database is full") is None


def _status(sock: str) -> dict[str, Any]:
    return call(sock, "GET", "/v1/status")  # type: ignore[no-any-return]


def _until(sock: str, proc: subprocess.Popen[bytes], ok: Any, log: Path) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    last: dict[str, Any] = {}
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()
        if Path(sock).exists():
            last = _status(sock)
            if ok(last):
                return last
        time.sleep(0.05)
    raise AssertionError(f"never as expected: {last}\n{log.read_text()}")


def test_a_missing_tracker_is_a_fault_until_it_answers(folder: Path) -> None:
    config = folder / "cell.toml"
    config.write_text(CONFIG)
    sock = str(folder / "run" / "control.sock")
    log = folder / "service.log"
    robot = standalone._twin("modbus-robot", "--listen", f"{ROBOT[0]}:{ROBOT[1]}")
    tracker = None
    with open(log, "w") as out:
        cmd = [sys.executable, "-m", "cellcal", "daemon", "--config", str(config)]
        cmd += ["--db", str(folder / "c.db"), "--socket", sock]
        service = subprocess.Popen(cmd, stdout=out, stderr=out)
    try:
        standalone._wait_listening(ROBOT, robot, 30.0)
        s = _until(sock, service, lambda s: s["devices"]["tracker"]["state"] == "fault", log)
        assert s["devices"]["robot"] == {"state": "connecting", "message": ""}
        message = s["devices"]["tracker"]["message"]
        assert TRACKER[0] in message and "\n" not in message
        assert s["state"] == "idle" and "tracker: fault" in s["reason"]
        tracker = standalone._twin("tracker", "--listen", f"{TRACKER[0]}:{TRACKER[1]}")
        standalone._wait_listening(TRACKER, tracker, 30.0)
        ready = lambda s: all(d["state"] == "ready" for d in s["devices"].values())  # noqa: E731
        s = _until(sock, service, ready, log)
        assert s["reason"] == "devices ready, no campaign running"
        assert "next attempt in" in log.read_text()
    finally:
        service.terminate()
        service.wait(30)
        for twin in (robot, tracker):
            if twin is not None:
                twin.kill()
                twin.wait(10)
