"""Fixtures of the service's tests: a fake systemd (a datagram socket that receives what
the service sends, with the sender's pid from SO_PASSCRED)."""

from __future__ import annotations

import os
import socket
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


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
