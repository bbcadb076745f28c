"""sd_notify against a fake systemd: a datagram socket that receives what the service
sends, with the sender's pid from SO_PASSCRED, on a path and in the abstract namespace."""

from __future__ import annotations

import logging
import os
import socket
import struct
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.daemon.sdnotify import Notifier

pytestmark = pytest.mark.timeout(30)


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
def fake() -> Iterator[tuple[FakeSystemd, str]]:
    # Unix socket paths are limited to 108 bytes: pytest's temp paths may be longer
    folder = tempfile.mkdtemp(prefix="cellcal-notify-", dir="/tmp")
    path = str(Path(folder) / "notify")
    f = FakeSystemd(path)
    yield f, path
    f.sock.close()
    os.unlink(path)
    os.rmdir(folder)


def test_ready_status_watchdog_stopping_reach_systemd(fake: tuple[FakeSystemd, str]) -> None:
    systemd, path = fake
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled and n.watchdog_interval_s is None
    assert n.ready("idle; devices: robot ready, tracker connecting")
    fields, pid = systemd.receive()
    assert fields == {"READY": "1", "STATUS": "idle; devices: robot ready, tracker connecting"}
    assert pid == os.getpid()
    assert n.status("running campaign 3: pose 12 of 80 — 7 s dwell, σ 0.8 µm")
    assert systemd.receive()[0] == {
        "STATUS": "running campaign 3: pose 12 of 80 — 7 s dwell, σ 0.8 µm"
    }
    assert n.watchdog() and systemd.receive()[0] == {"WATCHDOG": "1"}
    assert n.status("line one\nline two") and systemd.receive()[0] == {
        "STATUS": "line one line two"
    }
    assert n.reloading()
    fields, _ = systemd.receive()
    assert fields["RELOADING"] == "1" and int(fields["MONOTONIC_USEC"]) > 0
    assert n.stopping("stopping: SIGTERM") and systemd.receive()[0] == {
        "STOPPING": "1",
        "STATUS": "stopping: SIGTERM",
    }
    assert systemd.nothing_waiting()


def test_abstract_socket_name() -> None:
    name = f"cellcal-test-{uuid.uuid4().hex}"
    systemd = FakeSystemd("\0" + name)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert systemd.receive()[0] == {"READY": "1"}
    finally:
        systemd.sock.close()


def test_watchdog_interval_is_half_the_timeout_and_only_for_this_process() -> None:
    n = Notifier({"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "30000000"})
    assert n.watchdog_interval_s == 15.0
    mine = Notifier({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())})
    assert mine.watchdog_interval_s == 15.0
    other = Notifier({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_interval_s is None
    assert Notifier({"WATCHDOG_USEC": "x"}).watchdog_interval_s is None
    assert Notifier({"WATCHDOG_USEC": "0"}).watchdog_interval_s is None


def test_without_systemd_nothing_is_sent_and_a_gone_socket_never_raises() -> None:
    n = Notifier({})
    assert not n.enabled and not n.ready() and not n.watchdog()
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("cellcal.daemon.sdnotify")
    level = logger.level
    logger.setLevel(logging.WARNING)  # the CLI's tests leave the root logger at ERROR
    logger.addHandler(handler)
    try:
        gone = Notifier({"NOTIFY_SOCKET": "/tmp/cellcal-no-such-notify-socket"})
        assert not gone.ready() and not gone.status("x")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert len(records) == 1  # logged once, not per call
    assert records[0].getMessage().startswith("sd_notify to /tmp/cellcal-no-such-notify-socket")
