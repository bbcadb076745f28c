"""Where commands write when neither the command line nor the configuration names a
database: the user's data directory ($XDG_DATA_HOME/cellcal, else
~/.local/share/cellcal), never the configuration's folder or the working folder; and
they say where."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cellcal.commands.service_client import call

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.twin, pytest.mark.timeout(300)]


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _checkout(folder: Path) -> Path:
    """A working folder laid out as the repository: a copy of ``config``."""
    work = folder / "work"
    work.mkdir()
    shutil.copytree(ROOT / "config", work / "config")
    return work


def _env(home: Path, xdg: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("CELLCAL_SOCKET", "STATE_DIRECTORY")}
    env.pop("XDG_DATA_HOME", None)
    env["HOME"] = str(home)
    env["PYTHONPATH"] = str(ROOT)
    if xdg is not None:
        env["XDG_DATA_HOME"] = str(xdg)
    return env


def test_run_writes_into_the_user_data_directory_and_says_so(folder: Path) -> None:
    work = _checkout(folder)
    before = _files(work)
    xdg = folder / "xdg"
    cmd = [sys.executable, "-m", "cellcal", "run", "--mock"]
    done = subprocess.run(
        [*cmd, "--config", "config/mock-cell-tracker.toml"],
        cwd=work,
        env=_env(folder / "home", xdg),
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    db = xdg / "cellcal" / "cellcal.db"
    assert f"database: {db} (campaign 1)" in done.stdout
    assert db.is_file()
    assert _files(work) == before  # nothing beside the configuration, nothing in the cwd


def test_the_service_writes_into_the_user_data_directory_and_says_so(folder: Path) -> None:
    work = _checkout(folder)
    before = _files(work)
    home = folder / "home"
    sock = str(folder / "run" / "control.sock")
    cmd = [sys.executable, "-m", "cellcal", "daemon", "--mock"]
    cmd += ["--config", "config/mock-cell-tracker.toml", "--socket", sock]
    log_path = folder / "daemon.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            cmd, cwd=work, env=_env(home, None), stdout=log, stderr=log, text=True
        )
    try:
        deadline = time.monotonic() + 120
        status: dict[str, object] = {}
        started = False
        while time.monotonic() < deadline:
            assert proc.poll() is None, log_path.read_text()[-3000:]
            try:
                status = call(sock, "GET", "/v1/status")
            except Exception:
                time.sleep(0.1)
                continue
            if not started and status["state"] == "idle":
                call(sock, "POST", "/v1/campaigns", {})
                started = True
            campaign = status.get("campaign") or {}
            if started and isinstance(campaign, dict) and campaign.get("status") == "complete":
                break
            time.sleep(0.1)
        else:
            raise AssertionError(f"{status}\n{log_path.read_text()[-3000:]}")
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    data = home / ".local" / "share" / "cellcal"
    said = log_path.read_text()
    assert f"database {data / 'cellcal.db'} (the default" in said, said[-3000:]
    assert f"reports in {data / 'reports'}" in said
    assert (data / "cellcal.db").is_file()
    assert (data / "reports" / "campaign-1" / "index.html").is_file()
    assert _files(work) == before
