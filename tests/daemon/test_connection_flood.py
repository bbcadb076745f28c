"""A flood of idle connections to the status page leaves the service reachable
(issue 29: 1 100 of them took every file descriptor; the control socket could not
accept, asyncio logged 300 000 lines in 75 s, and a start that timed out on its
client's side ran 44 s later).

The service runs with its open files limit lowered to 256 (soft and hard: raising the
soft limit cannot help), which proves with 400 connections what 1 100 did against
1 024. The page takes its share of the descriptors and refuses the rest at once; the
control socket answers throughout; the log stays quiet; idle connections, on the page
and on the control socket, are closed after ``IDLE_TIMEOUT_S``."""

from __future__ import annotations

import logging
import os
import random
import resource
import select
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.commands.service_client import call
from tests.daemon.conftest import Daemon, serving

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(180)]

LIMIT = 256
FLOOD = 400
#: How long the service may take to close an idle connection (its idle timeout is 10 s).
CLOSED_WITHIN_S = 40.0


class LimitedDaemon(Daemon):
    """The service with RLIMIT_NOFILE lowered to ``LIMIT`` (soft and hard) in its process."""

    def start(self) -> None:
        launch = (
            "import resource, runpy, sys; "
            f"resource.setrlimit(resource.RLIMIT_NOFILE, ({LIMIT}, {LIMIT})); "
            "sys.argv = ['cellcal', *sys.argv[1:]]; "
            "runpy.run_module('cellcal', run_name='__main__')"
        )
        cmd = [sys.executable, "-c", launch, "daemon", "--mock", "--config", str(self.config)]
        cmd += ["--db", str(self.db), "--socket", self.sock, "--time-scale", "0.02"]
        cmd += self.extra
        self.log = open(self.folder / "daemon.log", "a")  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=self.log, text=True)
        self.until(lambda s: all(d["state"] == "ready" for d in s["devices"].values()), 90)


@pytest.fixture(scope="module")
def service() -> Iterator[LimitedDaemon]:
    # the test's own process holds the flood's sockets: room for them
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 4 * FLOOD:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4 * FLOOD), hard))
    folder = Path(tempfile.mkdtemp(prefix="cc-svc-", dir="/tmp"))
    address = f"127.0.0.{random.randint(2, 254)}"
    with serving(LimitedDaemon(folder, None, 0.02, ["--http", f"{address}:0"])) as d:
        yield d


def _page(d: Daemon) -> tuple[str, int]:
    url = call(d.sock, "GET", "/v1/info")["http"]  # http://127.0.0.x:port/
    host, port = url.removeprefix("http://").rstrip("/").rsplit(":", 1)
    return host, int(port)


def _connect(address: tuple[str, int] | str) -> socket.socket | None:
    family = socket.AF_UNIX if isinstance(address, str) else socket.AF_INET
    s = socket.socket(family, socket.SOCK_STREAM)
    s.settimeout(5)
    try:
        s.connect(address)
    except OSError:
        s.close()
        return None
    return s


def _all_closed_by_the_service(socks: list[socket.socket], within: float) -> bool:
    """Until every connection reads its end (EOF or a reset), at most ``within`` s."""
    deadline = time.monotonic() + within
    pending = list(socks)
    while pending and time.monotonic() < deadline:
        ready, _, _ = select.select(pending, [], [], 1.0)
        for s in ready:
            try:
                data = s.recv(65536)
            except OSError:
                data = b""
            if not data:  # an answer first (a 503) is read, then the end
                pending.remove(s)
    return not pending


def _log_lines(d: Daemon) -> int:
    return len((d.folder / "daemon.log").read_text().splitlines())


def test_a_flood_of_idle_page_connections(service: LimitedDaemon) -> None:
    page = _page(service)
    lines_before = _log_lines(service)
    flood = [s for s in (_connect(page) for _ in range(FLOOD)) if s is not None]
    try:
        assert len(flood) > LIMIT  # more than the service could ever have held
        # the control socket answers while the page is flooded (the client's timeout)
        for _ in range(5):
            assert call(service.sock, "GET", "/v1/status")["state"] == "idle"
        # the service is still there, and said so in a few lines, not thousands
        assert service.proc is not None and service.proc.poll() is None
        assert _log_lines(service) - lines_before < 20, service.tail()
        # every idle connection is closed by the service (refused at once or timed out)
        assert _all_closed_by_the_service(flood, CLOSED_WITHIN_S)
    finally:
        for s in flood:
            s.close()
    # and the page serves again
    again = _connect(page)
    assert again is not None
    with again:
        again.sendall(b"GET / HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        assert again.recv(64).startswith(b"HTTP/1.1 200")
    assert "Traceback" not in service.tail()


def test_idle_control_connections_are_closed(service: LimitedDaemon) -> None:
    """A client that connects to the control socket and says nothing, or drips its
    request, holds a descriptor for ``IDLE_TIMEOUT_S`` at most."""
    idle = [s for s in (_connect(service.sock) for _ in range(20)) if s is not None]
    drip = _connect(service.sock)
    assert drip is not None
    try:
        drip.sendall(b"GET /v1/status HTTP/1.1\r\nHo")  # and never the rest
        assert _all_closed_by_the_service([*idle, drip], CLOSED_WITHIN_S)
    finally:
        for s in [*idle, drip]:
            s.close()
    assert call(service.sock, "GET", "/v1/status")["state"] == "idle"


def test_failed_accepts_are_logged_once_in_a_while(caplog: pytest.LogCaptureFixture) -> None:
    """asyncio calls the loop's exception handler for every failed accept (up to the
    backlog's length each time the socket is ready): one line comes out of many."""
    import asyncio

    from cellcal.service.connections import ACCEPT_FAILED, AcceptErrors

    handler = AcceptErrors()
    loop = asyncio.new_event_loop()
    try:
        with caplog.at_level(logging.ERROR, "cellcal.service"):
            for _ in range(1000):
                error = OSError(24, os.strerror(24))
                handler(loop, {"message": ACCEPT_FAILED, "exception": error})
    finally:
        loop.close()
    lines = [r for r in caplog.records if "cannot accept" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in caplog.records]
