"""`cellcal mock kuka-kvp`, `kuka-eki` and `abb-rws` as processes (127.0.0.179), each
driven by its real driver as built from the configuration; `cellcal export robot-program`
writes what each controller runs."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.drivers.base import DeviceContext
from cellcal.drivers.kuka_kvp import KukaKvpOptions
from cellcal.errors import DeviceError
from cellcal.families import families
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(120)]

#: driver → (the fault option that makes its controller refuse a campaign, what it says)
REFUSED = {
    "kuka-kvp": (("--mode", "T1"), "connect refused: controller in T1"),
    "kuka-eki": (("--mode", "T2"), "connect refused: controller in T2"),
    "abb-rws": (("--opmode", "MANF"), "connect refused: controller in MANF"),
}


def _twin(tmp_path: Path, driver: str, *extra: str) -> tuple[subprocess.Popen[str], str]:
    twin = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", driver, "--listen", "127.0.0.179:0",
         "--time-scale", "0.01", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )  # fmt: skip
    assert twin.stdout is not None
    address = twin.stdout.readline().strip()  # printed once it listens
    assert "127.0.0.179:" in address, twin.stderr.read() if twin.stderr else ""
    return twin, address


def _stop(twin: subprocess.Popen[str]) -> None:
    twin.send_signal(signal.SIGTERM)
    twin.communicate(timeout=30)
    assert twin.returncode == 0


def _robot(driver: str, address: str) -> object:
    (family,) = [f for f in families("robot") if f.driver == driver]
    options = family.options_model()(address=address, poll_s=0.005)
    return family.device_class().from_options(options, DeviceContext())


@pytest.mark.parametrize("driver", sorted(REFUSED))
def test_the_mock_controller_moves_for_the_driver(tmp_path: Path, driver: str):
    if driver == "abb-rws":
        pytest.importorskip("httpx")
    twin, address = _twin(tmp_path, driver)
    try:
        robot = _robot(driver, address)
        with robot:  # type: ignore[attr-defined]
            home = robot.actual_joints()  # type: ignore[attr-defined]
            # the bundled cell's KR 5 arc, at its home
            np.testing.assert_allclose(np.degrees(home), [0, -30, 40, 0, -20, 0], atol=1e-4)
            robot.move_joints(home + np.radians([5, 5, -5, 10, 5, -10]), 0.5)  # type: ignore[attr-defined]
    finally:
        _stop(twin)


@pytest.mark.parametrize("driver", sorted(REFUSED))
def test_the_mock_controller_that_cannot_move_is_refused(tmp_path: Path, driver: str):
    if driver == "abb-rws":
        pytest.importorskip("httpx")
    fault, says = REFUSED[driver]
    twin, address = _twin(tmp_path, driver, *fault)
    try:
        with pytest.raises(DeviceError, match=says):
            _robot(driver, address).connect()  # type: ignore[attr-defined]
    finally:
        _stop(twin)


def test_export_the_krl_loop(tmp_path: Path):
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
    # a folder that is not there yet is made (as docs/robots.md's steps assume); a file
    # where the folder should be is refused
    made = cellcal("export", "robot-program", "--driver", "kuka-kvp", "--out", tmp_path / "a/b")
    assert made.returncode == 0 and (tmp_path / "a" / "b" / "CellCal.src").read_text() == src
    bad = cellcal(
        "export", "robot-program", "--driver", "kuka-kvp", "--out", tmp_path / "a/b/CellCal.src"
    )
    assert bad.returncode == 2 and bad.stderr.strip().endswith("exists and is not a folder")


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


def test_export_the_rapid_module(tmp_path: Path):
    done = cellcal("export", "robot-program", "--driver", "abb-rws", "--out", tmp_path)
    assert done.returncode == 0, done.stderr
    mod = (tmp_path / "CellCal.mod").read_text()
    for name in ("cc_target", "cc_seq", "cc_ack", "cc_speed"):
        assert f"PERS {'jointtarget' if name == 'cc_target' else 'num'} {name}" in mod
    assert "MoveAbsJ cc_target, v5000, fine, tool0" in mod and "WaitRob \\InPos" in mod
