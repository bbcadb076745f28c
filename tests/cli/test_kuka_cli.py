"""`cellcal mock kuka-kvp` and `kuka-eki` as processes (127.0.0.179), driven by the real
drivers; `cellcal export robot-program` writes what the controller runs."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.drivers.base import host_port
from cellcal.drivers.kuka_eki import KukaEkiOptions, KukaEkiRobot
from cellcal.drivers.kuka_kvp import KukaKvpOptions, KukaKvpRobot
from cellcal.errors import DeviceError
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(120)]

MOCK = (sys.executable, "-m", "cellcal", "mock", "kuka-kvp")


def _twin(
    tmp_path: Path, *extra: str, mock: tuple[str, ...] = MOCK
) -> tuple[subprocess.Popen[str], str]:
    twin = subprocess.Popen(
        [*mock, "--listen", "127.0.0.179:0", "--time-scale", "0.01", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    assert twin.stdout is not None
    address = twin.stdout.readline().strip()  # printed once it listens
    assert address.startswith("127.0.0.179:"), twin.stderr.read() if twin.stderr else ""
    return twin, address


def _stop(twin: subprocess.Popen[str]) -> None:
    twin.send_signal(signal.SIGTERM)
    twin.communicate(timeout=30)
    assert twin.returncode == 0


def test_the_mock_controller_moves_for_the_driver(tmp_path: Path):
    twin, address = _twin(tmp_path)
    try:
        host, port = host_port(address, 7000)
        robot = KukaKvpRobot(host, port, options=KukaKvpOptions(address=address, poll_s=0.005))
        with robot:
            home = robot.actual_joints()
            # the bundled cell's KR 5 arc, at its home
            np.testing.assert_allclose(np.degrees(home), [0, -30, 40, 0, -20, 0], atol=1e-4)
            robot.move_joints(home + np.radians([5, 5, -5, 10, 5, -10]), 0.5)
    finally:
        _stop(twin)


def test_the_mock_ethernetkrl_channel_moves_for_the_driver(tmp_path: Path):
    twin, address = _twin(tmp_path, mock=(*MOCK[:-1], "kuka-eki"))
    try:
        host, port = host_port(address, 54600)
        robot = KukaEkiRobot(host, port, options=KukaEkiOptions(address=address, poll_s=0.005))
        with robot:
            home = robot.actual_joints()
            np.testing.assert_allclose(np.degrees(home), [0, -30, 40, 0, -20, 0], atol=1e-5)
            robot.move_joints(home + np.radians([5, 5, -5, 10, 5, -10]), 0.5)
    finally:
        _stop(twin)


def test_the_mock_controller_in_t1_is_refused(tmp_path: Path):
    twin, address = _twin(tmp_path, "--mode", "T1")
    try:
        host, port = host_port(address, 7000)
        with pytest.raises(DeviceError, match="connect refused: controller in T1"):
            KukaKvpRobot(host, port).connect()
    finally:
        _stop(twin)


def test_export_the_ethernetkrl_program(tmp_path: Path):
    done = cellcal("export", "robot-program", "--driver", "kuka-eki", "--out", tmp_path)
    assert done.returncode == 0, done.stderr
    xml = (tmp_path / "CellCalEki.xml").read_text()
    src = (tmp_path / "CellCalEki.src").read_text()
    # every attribute the driver parses is declared as sent, every one it sends as received
    for attr in ("Seq", "Ack", "Mode", "Drives", "EStop", "GuardStop", "InMotion", "RobStopped"):
        assert f'Tag="CellCal/State/@{attr}"' in xml and f"CellCal/State/@{attr}" in src
    for attr in ("Seq", "Speed", "A1", "A6"):
        assert f'Tag="CellCal/Cmd/@{attr}"' in xml
    assert "<PORT>54600</PORT>" in xml and "PTP target" in src


def test_export_robot_program(tmp_path: Path):
    done = cellcal("export", "robot-program", "--driver", "kuka-kvp", "--out", tmp_path, "--json")
    assert done.returncode == 0, done.stderr
    files = json.loads(done.stdout)["files"]
    assert sorted(Path(f).name for f in files) == ["CellCal.src", "config.dat.txt"]
    src = (tmp_path / "CellCal.src").read_text()
    assert "PTP CC_TARGET" in src and "C_PTP CC_TARGET" not in src and "CC_ACK = seq" in src
    # every variable the driver uses by default is declared for $config.dat
    declared = (tmp_path / "config.dat.txt").read_text()
    o = KukaKvpOptions()
    for name in (o.target_var, o.seq_var, o.ack_var, o.speed_var, o.stop_var):
        assert f" {name}" in declared
    bad = cellcal("export", "robot-program", "--driver", "kuka-kvp", "--out", tmp_path / "no")
    assert bad.returncode == 2 and bad.stderr.strip().endswith("not a folder (create it first)")
