"""``cellcal campaign start --config FILE`` with the very file the service runs, from
another working folder: the file's relative paths (the rig's calibration and the flange
target) resolve against the file's folder on both sides, so the service accepts it; a
file whose rig really is another file is refused in one line."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.commands.service_client import call
from cellcal.errors import CellcalError
from tests.inprocess import cellcal

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"

pytestmark = [pytest.mark.twin, pytest.mark.timeout(240)]


def _cell(folder: Path) -> Path:
    """A verbatim copy of the bundled cell (rig_file and target_file relative) with its
    rig and target files, in ``folder``."""
    folder.mkdir(parents=True)
    for name in ("mock-cell.toml", "mock-rig.toml", "mock-target.toml"):
        shutil.copy(CONFIG / name, folder / name)
    return folder / "mock-cell.toml"


def _cli(
    monkeypatch: pytest.MonkeyPatch, cwd: Path, *args: str
) -> subprocess.CompletedProcess[str]:
    """``cellcal ARGS`` in the test's process (tests/inprocess.py), working in ``cwd``."""
    monkeypatch.delenv("CELLCAL_SOCKET", raising=False)
    with monkeypatch.context() as m:
        m.chdir(cwd)
        return cellcal(*args)


def _answers(sock: str) -> bool:
    """Whether a service answers its status call on ``sock`` (not yet: the socket is
    missing, refuses, or the call fails while it starts)."""
    if not Path(sock).exists():
        return False
    try:
        call(sock, "GET", "/v1/status")
    except (OSError, CellcalError):
        return False
    return True


@pytest.fixture
def service(folder: Path) -> Iterator[tuple[Path, str]]:
    """A --mock service started in the cell's folder with ``--config mock-cell.toml``
    (a relative path); the folder it runs in and its socket."""
    cell = _cell(folder / "cell").parent
    sock = str(folder / "run" / "control.sock")
    cmd = [sys.executable, "-m", "cellcal", "daemon", "--mock", "--config", "mock-cell.toml"]
    cmd += ["--db", str(folder / "c.db"), "--socket", sock, "--time-scale", "0.02"]
    with open(folder / "daemon.log", "w") as log:
        proc = subprocess.Popen(cmd, cwd=cell, stdout=log, stderr=log, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while not _answers(sock):  # waits for the listening socket, never a fixed time
            assert proc.poll() is None, (folder / "daemon.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the service never answered on its socket"
            time.sleep(0.05)
        yield cell, sock
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def test_the_services_own_file_from_another_folder_is_accepted(
    folder: Path, service: tuple[Path, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cell, sock = service
    elsewhere = folder / "elsewhere"
    other = _cell(folder / "other")  # the same text, but its rig and target are other files
    elsewhere.mkdir()

    refused = _cli(
        monkeypatch, elsewhere, "campaign", "start", "--config", str(other), "--socket", sock
    )
    assert refused.returncode == 2, refused
    lines = refused.stderr.strip().splitlines()
    assert len(lines) == 1 and "[sensor] differs from the service's configuration" in lines[0]

    # the service's file, named by a relative path from a folder that is not the service's
    relative = os.path.relpath(cell / "mock-cell.toml", elsewhere)
    done = _cli(monkeypatch, elsewhere, "campaign", "start", "--config", relative, "--socket", sock)
    assert done.returncode == 0, done.stderr
    assert "campaign 1 accepted" in done.stdout
