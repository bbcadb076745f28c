"""`cellcal mock abb-rws` as a process (127.0.0.190), driven by the real driver;
`cellcal export robot-program --driver abb-rws` writes the RAPID module."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.drivers.abb_rws import AbbRwsOptions, AbbRwsRobot
from cellcal.errors import DeviceError
from tests.inprocess import cellcal

pytest.importorskip("httpx")
pytestmark = [pytest.mark.twin, pytest.mark.timeout(120)]

MOCK = (sys.executable, "-m", "cellcal", "mock", "abb-rws")


def _twin(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen[str], str]:
    twin = subprocess.Popen(
        [*MOCK, "--listen", "127.0.0.190:0", "--time-scale", "0.01", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    assert twin.stdout is not None
    address = twin.stdout.readline().strip()  # printed once it listens
    assert address.startswith("http://127.0.0.190:"), twin.stderr.read() if twin.stderr else ""
    return twin, address


def _stop(twin: subprocess.Popen[str]) -> None:
    twin.send_signal(signal.SIGTERM)
    twin.communicate(timeout=30)
    assert twin.returncode == 0


def test_the_mock_controller_moves_for_the_driver(tmp_path: Path):
    twin, address = _twin(tmp_path)
    try:
        robot = AbbRwsRobot(AbbRwsOptions(address=address, poll_s=0.005))
        with robot:
            home = robot.actual_joints()
            np.testing.assert_allclose(np.degrees(home), [0, -30, 40, 0, -20, 0], atol=1e-5)
            robot.move_joints(home + np.radians([5, 5, -5, 10, 5, -10]), 0.5)
            assert robot.describe().model == "kuka-kr5-arc"  # the simulated cell's robot
    finally:
        _stop(twin)


def test_the_mock_controller_in_manual_mode_is_refused(tmp_path: Path):
    twin, address = _twin(tmp_path, "--opmode", "MANF")
    try:
        with pytest.raises(DeviceError, match="connect refused: controller in MANF"):
            AbbRwsRobot(AbbRwsOptions(address=address)).connect()
    finally:
        _stop(twin)


def test_export_the_rapid_module(tmp_path: Path):
    done = cellcal("export", "robot-program", "--driver", "abb-rws", "--out", tmp_path)
    assert done.returncode == 0, done.stderr
    mod = (tmp_path / "CellCal.mod").read_text()
    for name in ("cc_target", "cc_seq", "cc_ack", "cc_speed"):
        assert f"PERS {'jointtarget' if name == 'cc_target' else 'num'} {name}" in mod
    assert "MoveAbsJ cc_target, v5000, fine, tool0" in mod and "WaitRob \\InPos" in mod
