"""The claim on a robot: two campaigns on two databases never drive one robot. The
service in real mode against standalone twins holds the robot's claim for its life; a
``cellcal run`` on another database and a second service are refused with one line that
names the holder, before anything connects or is written; once the service has stopped
the claim is free and remembers who held it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.campaign.locks import RobotClaim
from cellcal.commands.service_client import call
from cellcal.errors import CampaignError
from tests.e2e import test_standalone_twins as standalone

TRACKER = ("127.0.0.75", 5555)
ROBOT = ("127.0.0.76", 1502)
CONFIG = standalone.config_on(TRACKER, ROBOT)

pytestmark = [pytest.mark.twin, pytest.mark.timeout(180)]


def test_a_claim_is_exclusive_and_names_its_holder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CELLCAL_LOCK_DIR", str(tmp_path))
    with RobotClaim("modbus", "10.0.0.5:502", "cellcal run on /data/a.db"):
        who = rf"cellcal run on /data/a.db \(pid {os.getpid()}\)"
        with (
            pytest.raises(
                CampaignError, match=rf"modbus robot at 10.0.0.5:502 is claimed by {who}"
            ),
            RobotClaim("modbus", "10.0.0.5:502", "cellcal run on /data/b.db"),
        ):
            pytest.fail("a second claim on one robot")
        with RobotClaim("modbus", "10.0.0.6:502", "another robot") as other:
            assert other.fd is not None  # another robot: its own claim
    with RobotClaim("modbus", "10.0.0.5:502", "next") as claim:
        assert claim.previous.startswith("cellcal run on /data/a.db")
    (path,) = [p for p in tmp_path.iterdir() if "10.0.0.5" in p.name]
    assert path.stat().st_mode & 0o666 == 0o666  # the next holder may be another user
    monkeypatch.setenv("CELLCAL_LOCK_DIR", str(tmp_path / "none"))
    with pytest.raises(CampaignError, match="CELLCAL_LOCK_DIR"):
        RobotClaim("modbus", "x", "y").__enter__()


@pytest.fixture
def twins() -> Iterator[None]:
    procs = [
        standalone._twin("tracker", "--listen", f"{TRACKER[0]}:{TRACKER[1]}"),
        standalone._twin("modbus-robot", "--listen", f"{ROBOT[0]}:{ROBOT[1]}"),
    ]
    try:
        standalone._wait_listening(TRACKER, procs[0], 30.0)
        standalone._wait_listening(ROBOT, procs[1], 30.0)
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait(10)


def test_the_service_claims_its_robot_against_every_other_database(
    folder: Path, twins: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = folder / "cell.toml"
    config.write_text(CONFIG)
    env = dict(os.environ, CELLCAL_LOCK_DIR=str(folder))
    sock = str(folder / "run" / "control.sock")
    cli = [sys.executable, "-m", "cellcal"]
    log = open(folder / "service.log", "w")  # noqa: SIM115
    service = subprocess.Popen(
        [*cli, "daemon", "--config", str(config), "--db", str(folder / "a.db"), "--socket", sock],
        stdout=log,
        stderr=log,
        env=env,
    )
    try:
        deadline = time.monotonic() + 60
        ready = False
        while not ready and time.monotonic() < deadline:
            assert service.poll() is None, (folder / "service.log").read_text()
            if Path(sock).exists():
                status = call(sock, "GET", "/v1/status")
                ready = all(d["state"] == "ready" for d in status["devices"].values())
            time.sleep(0.05)
        assert ready, (folder / "service.log").read_text()
        holder = f"the cellcal service on {folder / 'a.db'} (pid {service.pid})"
        for args in (
            ["run", "--config", str(config), "--db", str(folder / "b.db")],
            [
                "daemon",
                "--config",
                str(config),
                "--db",
                str(folder / "c.db"),
                "--socket",
                str(folder / "c.sock"),
            ],
        ):
            res = subprocess.run([*cli, *args], capture_output=True, text=True, env=env, timeout=60)
            assert res.returncode == 2, res.stderr
            # one line, the last; `run` says what it is doing before it
            *progress, line = res.stderr.strip().splitlines()
            assert "is claimed by" in line, line
            assert len(progress) == (args[0] == "run"), progress
            assert f"modbus robot at {ROBOT[0]}:{ROBOT[1]}" in line and holder in line, line
        assert not (folder / "b.db").exists() or (folder / "b.db").stat().st_size == 0
        service.send_signal(signal.SIGTERM)
        assert service.wait(30) == 0
    finally:
        if service.poll() is None:
            service.kill()
        log.close()
    monkeypatch.setenv("CELLCAL_LOCK_DIR", str(folder))
    with RobotClaim("modbus", f"{ROBOT[0]}:{ROBOT[1]}", "test") as claim:
        assert claim.previous == holder
