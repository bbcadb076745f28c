"""Hostile databases (issue 29): whatever file ``--db`` names — SQLite's special names,
an empty path, a truncated file, random bytes, a SQLite file whose tables lack columns,
a wrong ``user_version``, damaged pages, a locked or a read-only file — every command
that reads or writes a database (``run``, ``run --resume``, ``report``, ``campaign
list``, the service at start) ends with one line naming the file and what is wrong,
exit 2: never a traceback, never a campaign into memory, never the config's database
instead of the one asked for."""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.inprocess import cellcal

ROOT = Path(__file__).resolve().parents[1]
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(autouse=True)
def _private_data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The user's data directory (the config's default database) in the test's folder,
    and the test's folder as the working one: what a command writes by mistake lands
    there, where the test can see it."""
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.chdir(tmp_path)


@pytest.fixture(scope="module")
def real_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real cellcal database: the tracker cell's campaign, complete (campaign 1)."""
    folder = tmp_path_factory.mktemp("real")
    db = folder / "real.db"
    done = cellcal("run", "--config", TRACKER_CELL, "--mock", "--db", db, "--seed", "11")
    assert done.returncode == 0, done.stderr
    return db


def _ends_in_one_line(done: subprocess.CompletedProcess[str], *needles: str) -> str:
    """Exit 2, no traceback, and stderr ends with the one error line, which holds every
    needle (a progress line of ``run`` may come before it)."""
    err = done.stderr.strip().splitlines()
    assert "Traceback" not in done.stderr, done.stderr
    assert done.returncode == 2, (done.returncode, done.stderr)
    errors = [line for line in err if line.startswith("cellcal: error: ")]
    assert len(errors) == 1 and errors[0] == err[-1] and len(err) <= 2, err
    for needle in needles:
        assert needle in err[-1], (needle, err[-1])
    return err[-1]


# -- special names and an empty path ----------------------------------------------------


SPECIAL = {
    ":memory:": "memory",
    "": "empty",
    "file:campaign.db": "URI",
    "file::memory:?cache=shared": "URI",
    "FILE:campaign.db?mode=rwc": "URI",
    ":temp:": "reserved",
}


@pytest.mark.parametrize("name", list(SPECIAL))
def test_run_refuses_special_names_and_an_empty_path(tmp_path: Path, name: str) -> None:
    done = cellcal("run", "--config", TRACKER_CELL, "--mock", "--db", name)
    _ends_in_one_line(done, SPECIAL[name])
    assert not (tmp_path / "xdg").exists(), "the config's database was used instead"
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "a file was made"


@pytest.mark.parametrize("name", [":memory:", ""])
def test_resume_report_and_list_refuse_special_names(tmp_path: Path, name: str) -> None:
    for argv in (
        ["run", "--resume", "1", "--db", name],
        ["report", "--db", name, "--out", str(tmp_path / "report")],
        ["campaign", "list", "--db", name],
    ):
        _ends_in_one_line(cellcal(*argv), SPECIAL[name])
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.twin
@pytest.mark.parametrize(("name", "said"), [(":memory:", "memory"), ("", "empty")])
def test_the_service_refuses_an_in_memory_database(
    tmp_path: Path, name: str, said: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = Path(tempfile.mkdtemp(prefix="cellcal-db-", dir="/tmp"))  # a short socket path
    try:
        done = _service(folder, name, monkeypatch)  # in tmp_path, the working folder
        line = _service_error(done)
        assert said in line, line
        assert not (tmp_path / ":memory:").exists()
        assert not (tmp_path / ":memory:.lock").exists()
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- damaged and foreign files ----------------------------------------------------------


def _truncated(src: Path, dst: Path) -> None:
    shutil.copy(src, dst)
    os.truncate(dst, 40000)


def _random_bytes(src: Path, dst: Path) -> None:
    dst.write_bytes(random.Random(1).randbytes(300_000))


def _sql(*statements: str) -> Callable[[Path, Path], None]:
    def make(src: Path, dst: Path) -> None:
        shutil.copy(src, dst)
        conn = sqlite3.connect(dst)
        for s in statements:
            conn.execute(s)
        conn.commit()
        conn.close()

    return make


def _damaged_pages(src: Path, dst: Path) -> None:
    """Random bytes over the pages in the middle of a real database (its samples)."""
    data = bytearray(src.read_bytes())
    page = 4096
    pages = len(data) // page
    rng = random.Random(2)
    for k in range(int(pages * 0.4), int(pages * 0.6)):
        data[k * page : (k + 1) * page] = rng.randbytes(page)
    dst.write_bytes(bytes(data))


DAMAGED: dict[str, tuple[Callable[[Path, Path], None], str]] = {
    "truncated": (_truncated, "damaged"),
    "random bytes": (_random_bytes, "not a cellcal database"),
    "a missing column": (_sql("ALTER TABLE poses DROP COLUMN reached_q_deg"), "reached_q_deg"),
    "a missing table": (_sql("DROP TABLE pose_stats"), "pose_stats"),
    "an older user_version": (_sql("PRAGMA user_version = 2"), "user_version"),
    "a negative user_version": (_sql("PRAGMA user_version = -5"), "user_version"),
    "a newer user_version": (_sql("PRAGMA user_version = 99"), "newer"),
    "damaged pages": (_damaged_pages, "damaged"),
}


@pytest.fixture(params=list(DAMAGED))
def damaged(request: pytest.FixtureRequest, real_db: Path, tmp_path: Path) -> tuple[Path, str]:
    make, needle = DAMAGED[request.param]
    path = tmp_path / "damaged.db"
    make(real_db, path)
    return path, needle


@pytest.mark.twin
def test_every_command_names_the_damaged_file_in_one_line(
    damaged: tuple[Path, str], tmp_path: Path
) -> None:
    path, needle = damaged
    before = path.read_bytes()
    _ends_in_one_line(cellcal("run", "--resume", "1", "--db", path), str(path), needle)
    _ends_in_one_line(
        cellcal("run", "--config", TRACKER_CELL, "--mock", "--db", path), str(path), needle
    )
    report = tmp_path / "report"
    _ends_in_one_line(cellcal("report", "--db", path, "--out", report), str(path), needle)
    # even where the listing would not meet the damage
    _ends_in_one_line(cellcal("campaign", "list", "--db", path), str(path), needle)
    assert path.read_bytes() == before, "a damaged or foreign file was changed"


@pytest.mark.twin
def test_the_service_names_the_damaged_file_at_start(
    damaged: tuple[Path, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, needle = damaged
    folder = Path(tempfile.mkdtemp(prefix="cellcal-db-", dir="/tmp"))
    try:
        line = _service_error(_service(folder, str(path), monkeypatch))
        assert str(path) in line and needle in line, line
    finally:
        shutil.rmtree(folder, ignore_errors=True)


#: How long the service started in the test's process may run: it is to end at start.
SERVICE_START_S = 60.0


def _service(
    folder: Path, db: str, monkeypatch: pytest.MonkeyPatch
) -> subprocess.CompletedProcess[str]:
    """The service started on ``db`` in the test's process (tests/inprocess.py), without
    systemd, its data directory in ``folder``, for SERVICE_START_S at most; the open files
    limit it raises at start is put back. (The locked database's test starts it as a
    process of its own.)"""
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)  # STATE_DIRECTORY: _private_data_dir
    monkeypatch.setenv("XDG_DATA_HOME", str(folder / "xdg"))
    run = asyncio.run

    def bounded(main: Coroutine[Any, Any, int]) -> int:
        """The service's loop; past SERVICE_START_S the service is stopped as systemd
        would, SIGTERM (once its loop handles it; cancelled before)."""

        async def within() -> int:
            task = asyncio.current_task()
            assert task is not None

            def stop() -> None:
                handler = getattr(signal.getsignal(signal.SIGTERM), "__name__", "")
                if handler == "_sighandler_noop":  # asyncio's: the service's handler
                    signal.raise_signal(signal.SIGTERM)
                else:
                    task.cancel()

            asyncio.get_running_loop().call_later(SERVICE_START_S, stop)
            return await main

        return run(within())

    monkeypatch.setattr(asyncio, "run", bounded)
    limits = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        return cellcal(
            *("daemon", "--config", TRACKER_CELL, "--mock", "--db", db),
            *("--socket", folder / "control.sock"),
        )
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, limits)


def _service_error(done: subprocess.CompletedProcess[str]) -> str:
    """The service ends at start with exit 2 and its last line is the one error."""
    assert "Traceback" not in done.stderr, done.stderr
    assert done.returncode == 2, (done.returncode, done.stderr)
    err = done.stderr.strip().splitlines()
    assert [line for line in err if line.startswith("cellcal: error: ")] == [err[-1]], err
    return err[-1]


# -- a locked database, a read-only one -------------------------------------------------


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Another program holds ``path`` locked (an exclusive transaction, rollback journal)."""
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("PRAGMA journal_mode=DELETE")
    conn.execute("BEGIN EXCLUSIVE")
    try:
        yield
    finally:
        conn.execute("ROLLBACK")
        conn.close()


def _subprocess(*argv: object, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "cellcal", *map(str, argv)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
    )


def _finish(p: subprocess.Popen[str]) -> subprocess.CompletedProcess[str]:
    out, err = p.communicate(timeout=120)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


@pytest.mark.slow
@pytest.mark.twin
def test_a_locked_database_is_named_in_one_line(real_db: Path, tmp_path: Path) -> None:
    path = tmp_path / "locked.db"
    shutil.copy(real_db, path)
    folder = Path(tempfile.mkdtemp(prefix="cellcal-db-", dir="/tmp"))  # a short socket path
    try:
        with _locked(path):
            # together: each waits for the lock (the busy timeout) before it says so
            running = [
                _subprocess("run", "--resume", "1", "--db", path, cwd=tmp_path),
                _subprocess("report", "--db", path, "--out", tmp_path / "report", cwd=tmp_path),
                _subprocess("campaign", "list", "--db", path, cwd=tmp_path),
            ]
            service = _subprocess(
                *("daemon", "--config", TRACKER_CELL, "--mock", "--db", path),
                *("--socket", folder / "control.sock"),
                cwd=tmp_path,
            )
            done = [_finish(p) for p in running]
            started = _finish(service)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    for d in done:
        _ends_in_one_line(d, str(path), "locked")
    line = _service_error(started)
    assert str(path) in line and "locked" in line, line


def _read_only(path: Path) -> contextlib.AbstractContextManager[None]:
    """``path`` read-only for this process: its mode (or, for root, whom the mode does not
    stop, the immutable attribute)."""

    @contextlib.contextmanager
    def mode() -> Iterator[None]:
        path.chmod(0o444)
        try:
            yield
        finally:
            path.chmod(0o644)

    @contextlib.contextmanager
    def immutable() -> Iterator[None]:
        if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode != 0:
            pytest.skip("root, and no immutable attribute here (chattr)")
        try:
            yield
        finally:
            subprocess.run(["chattr", "-i", str(path)], check=True)

    return immutable() if os.geteuid() == 0 else mode()


@pytest.mark.twin
def test_a_read_only_database_is_read_and_not_written(real_db: Path, tmp_path: Path) -> None:
    path = tmp_path / "read-only.db"
    shutil.copy(real_db, path)
    with _read_only(path):
        before = path.read_bytes()
        listed = cellcal("campaign", "list", "--db", path)
        assert listed.returncode == 0 and "complete" in listed.stdout, listed.stderr
        report = cellcal("report", "--db", path, "--out", tmp_path / "report")
        assert report.returncode == 0, report.stderr
        _ends_in_one_line(cellcal("run", "--resume", "1", "--db", path), str(path), "read-only")
        _ends_in_one_line(
            cellcal("run", "--config", TRACKER_CELL, "--mock", "--db", path),
            str(path),
            "read-only",
        )
        assert path.read_bytes() == before


def test_iso9283_refuses_an_empty_database_path() -> None:
    """`--db ""` is refused, not replaced by the configuration's database."""
    from tests.inprocess import cellcal

    res = cellcal("iso9283", "--mock", "--model", "kuka-kr5-arc", "--db", "")
    assert res.returncode == 2, res.stderr
    assert "empty" in res.stderr.strip().splitlines()[-1]
