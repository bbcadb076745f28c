"""The control socket's folder must be the service's own (issue 29): a folder another
user made first — the docs' own ``/tmp/cellcal`` — handed that user the service (the
socket took the folder's group, and the service admits its members). The service
refuses at start, in one line, a socket folder that is not its user's (or root's), or
that its group or everyone may write in (the sticky bit does not make it the service's)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cellcal.errors import CampaignError
from cellcal.service.daemon import socket_folder
from tests.daemon.conftest import TRACKER_CELL

NOBODY = 65534
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder away needs root")


def _folder(tmp_path: Path, mode: int, owner: int | None = None) -> Path:
    folder = tmp_path / "run"
    folder.mkdir()
    os.chmod(folder, mode)
    if owner is not None:
        os.chown(folder, owner, owner)
    return folder


def _refused(folder: Path, words: str) -> None:
    with pytest.raises(CampaignError, match=words) as refused:
        socket_folder(str(folder / "control.sock"))
    assert str(folder) in str(refused.value)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("mode", [0o770, 0o775, 0o730])
def test_a_folder_its_group_may_write_in_is_refused(tmp_path: Path, mode: int) -> None:
    _refused(_folder(tmp_path, mode), "writable by its group")


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o757])
def test_a_folder_everyone_may_write_in_is_refused(tmp_path: Path, mode: int) -> None:
    _refused(_folder(tmp_path, mode), "writable by everyone")


@as_root
def test_a_folder_of_another_user_is_refused(tmp_path: Path) -> None:
    _refused(_folder(tmp_path, 0o750, NOBODY), "belongs to .*65534")


@as_root
def test_a_link_of_another_user_is_refused(tmp_path: Path) -> None:
    """A link another user made to a folder of ours: they may point it elsewhere later."""
    ours = _folder(tmp_path, 0o750)
    link = tmp_path / "link"
    link.symlink_to(ours)
    os.lchown(link, NOBODY, NOBODY)
    _refused(link, "belongs to .*65534")


@pytest.mark.parametrize("mode", [0o700, 0o750, 0o755])
def test_a_folder_of_its_own_is_taken(tmp_path: Path, mode: int) -> None:
    folder = _folder(tmp_path, mode)
    assert socket_folder(str(folder / "control.sock")) == folder


def test_a_missing_folder_is_made_0750(tmp_path: Path) -> None:
    folder = tmp_path / "a" / "run"
    assert socket_folder(str(folder / "control.sock")) == folder
    assert folder.stat().st_mode & 0o777 == 0o750


@pytest.mark.twin
@pytest.mark.timeout(60)
def test_the_service_refuses_to_start_in_one_line(tmp_path: Path) -> None:
    """The service as a subprocess, its socket in a folder everyone may write in (as a
    ``/tmp/cellcal`` made by whoever came first): one line, exit 2, nothing listens."""
    folder = _folder(tmp_path, 0o1777)
    sock = folder / "control.sock"
    cmd = [sys.executable, "-m", "cellcal", "daemon", "--mock", "--config", str(TRACKER_CELL)]
    cmd += ["--socket", str(sock)]
    cmd += ["--db", str(tmp_path / "c.db")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=45)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("cellcal: error: "), done.stderr
    assert str(folder) in lines[0] and "writable by everyone" in lines[0], lines
    assert not sock.exists()
    assert not (tmp_path / "c.db").exists()
