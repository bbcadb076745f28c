"""Fixtures of the service's tests: a fake systemd (a datagram socket that receives what
the service sends, with the sender's pid from SO_PASSCRED); the service as a subprocess
in mock mode (the bundled cell's tracker alone), in a short folder under /tmp."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from tests.browser import shared_chromium  # noqa: F401  (the page tests' one browser)

ROOT = Path(__file__).resolve().parents[2]
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"


class FakeSystemd:
    def __init__(self, address: str | bytes) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self.sock.bind(address)
        self.sock.settimeout(5.0)

    def receive(self) -> tuple[dict[str, str], int]:
        """One notification's fields and the sender's pid."""
        size = struct.calcsize("3i")
        data, ancillary, _, _ = self.sock.recvmsg(4096, socket.CMSG_SPACE(size))
        pid = -1
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
                pid = struct.unpack("3i", payload[:size])[0]
        lines = data.decode("utf-8").splitlines()
        return dict(line.split("=", 1) for line in lines), pid

    def nothing_waiting(self) -> bool:
        self.sock.settimeout(0.05)
        try:
            self.sock.recv(4096)
        except TimeoutError:
            return True
        finally:
            self.sock.settimeout(5.0)
        return False


@pytest.fixture
def systemd_class() -> type[FakeSystemd]:
    return FakeSystemd


@pytest.fixture
def fake() -> Iterator[tuple[FakeSystemd, str]]:
    # Unix socket paths are limited to 108 bytes: pytest's temp paths may be longer
    folder = tempfile.mkdtemp(prefix="cellcal-notify-", dir="/tmp")
    path = str(Path(folder) / "notify")
    f = FakeSystemd(path)
    yield f, path
    f.sock.close()
    os.unlink(path)
    os.rmdir(folder)


class _UnixHTTP(http.client.HTTPConnection):
    """HTTP/1.1 over the service's Unix socket."""

    def __init__(self, path: str, timeout: float) -> None:
        super().__init__("cellcal", timeout=timeout)
        self._path = path

    def connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(self.timeout)
        try:
            sock.connect(self._path)
        except OSError:
            sock.close()
            raise
        self.sock = sock


def read_status(sock: str, timeout: float = 10.0) -> dict[str, Any]:
    """``GET /v1/status`` with the standard library's HTTP client: the tests poll the
    status while a service works (:meth:`Daemon.until`), and cellcal's own client
    (aiohttp, an event loop a call) costs about three times the CPU a poll (1.6 ms
    against 0.5 ms, the service's part included). The command-line client is tested by
    the CLI's tests; this one only reads."""
    conn = _UnixHTTP(sock, timeout)
    try:
        conn.request("GET", "/v1/status")
        resp = conn.getresponse()
        body = resp.read()
    finally:
        conn.close()
    data = json.loads(body)
    if resp.status != 200 or not isinstance(data, dict):
        raise AssertionError(f"GET /v1/status answered {resp.status}: {body[:200]!r}")
    return data


class Daemon:
    def __init__(
        self,
        folder: Path,
        notify: str | None,
        time_scale: float,
        extra: Sequence[str] = (),
        config: Path = TRACKER_CELL,
        new_session: bool = False,
    ) -> None:
        self.folder = folder
        # a session of its own: its process group stands for a terminal's foreground group
        self.new_session = new_session
        self.extra = list(extra)
        self.config = config
        self.db = folder / "c.db"
        self.sock = str(folder / "run" / "control.sock")
        self.notify = notify
        self.time_scale = time_scale
        self.proc: subprocess.Popen[str] | None = None

    def kill(self) -> None:
        """SIGKILL the service if it still runs, and reap it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def start(self) -> None:
        env = dict(os.environ)
        if self.notify:
            env.update(NOTIFY_SOCKET=self.notify, WATCHDOG_USEC="1000000")
        cmd = [sys.executable, "-m", "cellcal", "daemon", "--mock", "--config", str(self.config)]
        cmd += ["--db", str(self.db), "--socket", self.sock, "--time-scale", str(self.time_scale)]
        cmd += self.extra
        self.log = open(self.folder / "daemon.log", "a")  # noqa: SIM115
        self.proc = subprocess.Popen(
            cmd,
            stdout=self.log,
            stderr=self.log,
            text=True,
            env=env,
            start_new_session=self.new_session,
        )
        self.until(lambda s: all(d["state"] == "ready" for d in s["devices"].values()), 90)

    def status(self) -> dict[str, Any]:
        """The service's status, read by :func:`read_status` (the polls' cheap client)."""
        return read_status(self.sock)

    def until(self, ok: Callable[[dict[str, Any]], bool], timeout: float = 60) -> dict[str, Any]:
        """Poll the status until ``ok``; the listening socket is waited for the same way.
        The polls come every 10 ms at first, then less often, every 100 ms at most: a
        condition that holds soon is seen soon, and a long wait costs the service and
        the test little CPU."""
        deadline = time.monotonic() + timeout
        last: dict[str, Any] = {}
        pause = 0.01
        while time.monotonic() < deadline:
            assert self.proc is not None and self.proc.poll() is None, self.tail()
            if Path(self.sock).exists():
                try:
                    last = self.status()
                except Exception as exc:
                    last = {"error": repr(exc)}
                if "error" not in last and ok(last):
                    return last
            time.sleep(pause)
            pause = min(pause * 1.5, 0.1)
        raise AssertionError(f"status never as expected: {last}\n{self.tail()}")

    def rows(self, sql: str) -> list[tuple[Any, ...]]:
        with sqlite3.connect(self.db) as conn:
            return conn.execute(sql).fetchall()

    def tail(self) -> str:
        """The log's end, for a failure's message: long enough to reach back over a
        restart (a resumed rig campaign whose cameras gave no frame was seen once, with
        only its last 3000 characters: the restart itself was cut off)."""
        return (self.folder / "daemon.log").read_text()[-12000:]

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30) -> int:
        assert self.proc is not None
        self.proc.send_signal(sig)
        code = self.proc.wait(timeout)
        self.log.close()
        return code


def small_cell(folder: Path) -> Path:
    """The tracker cell on a 3×3×3 cube with 16 validation poses (43 poses, not 128):
    for the tests about the service's states, which need a campaign to run and end but
    not the paper's 80 calibration poses; written into ``folder``."""
    text = TRACKER_CELL.read_text(encoding="utf-8")
    for old, new in (
        ("grid = [4, 4, 5]", "grid = [3, 3, 3]"),
        ("validation_inside = 20", "validation_inside = 6"),
        ("validation_per_region = 6", "validation_per_region = 2"),
    ):
        assert old in text, old
        text = text.replace(old, new)
    path = folder / "small-cell.toml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def locks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder of the test's own for the robots' claims and the databases' run locks
    (``$CELLCAL_LOCK_DIR``), instead of /run/lock."""
    folder = tmp_path / "locks"
    folder.mkdir()
    monkeypatch.setenv("CELLCAL_LOCK_DIR", str(folder))
    return folder


@pytest.fixture
def folder() -> Iterator[Path]:
    # Unix socket paths are limited to 108 bytes: pytest's temp paths may be longer
    path = Path(tempfile.mkdtemp(prefix="cc-svc-", dir="/tmp"))
    yield path
    subprocess.run(["rm", "-rf", str(path)], check=False)


@pytest.fixture
def daemon() -> Iterator[Callable[..., Daemon]]:
    """Makes services (``Daemon(folder, notify, time_scale, extra)``); any still running
    at the end of the test is killed."""
    made: list[Daemon] = []

    def make(*args: Any, **kwargs: Any) -> Daemon:
        d = Daemon(*args, **kwargs)
        made.append(d)
        return d

    yield make
    for d in made:
        d.kill()


@contextlib.contextmanager
def serving(d: Daemon) -> Iterator[Daemon]:
    """``d`` started; at the end killed if it still runs, and its folder removed (for
    module fixtures, which cannot use ``folder`` and ``daemon``)."""
    try:
        d.start()
        yield d
    finally:
        d.kill()
        subprocess.run(["rm", "-rf", str(d.folder)], check=False)
