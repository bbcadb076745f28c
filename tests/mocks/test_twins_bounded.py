"""The twins against long and hostile clients (issue 29): what a twin keeps for a client
is bounded — an endless line without a newline, requests sent faster than their replies
are read, a long client's record of requests — and what it drops or closes it says in a
log line."""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import struct
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from cellcal.mocks import link_server
from cellcal.mocks.modbus.server import ModbusRobotTwin
from cellcal.mocks.tracker.server import TrackerTwin
from cellcal.mocks.ur import rtde_codec as rtde
from cellcal.mocks.ur import script_port as ur_script_port
from cellcal.mocks.ur.rtde_session import RtdeSession
from cellcal.mocks.ur.script_port import MAX_PROGRAM, ScriptReader

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(60)]

TRACKER_HOST = "127.0.0.142"
MODBUS_HOST = "127.0.0.143"


class Target:
    def sample(self, n: int) -> np.ndarray:
        return np.tile([1000.0, 0.0, 500.0], (n, 1))


def wait_until(predicate: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.01)


def _stingy(address: tuple[str, int]) -> socket.socket:
    """A client connection with 4 KiB socket buffers (set before it connects): a client
    that never reads stalls the twin's writes after a few replies, not after the
    megabytes of replies that the kernel's buffers would take by default — the same
    stall, found with a fraction of the work."""
    client = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    client.settimeout(5.0)
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        client.setsockopt(socket.SOL_SOCKET, option, 4096)
    client.connect(address)
    return client


@contextlib.contextmanager
def _tracker() -> Iterator[tuple[TrackerTwin, socket.socket, tuple[str, int]]]:
    server = TrackerTwin(Target())
    address = server.start_tcp(TRACKER_HOST, 0)  # listening once it returns
    client = _stingy(address)
    try:
        yield server, client, address
    finally:
        client.close()
        server.stop()


def _flood(client: socket.socket, request: bytes, gone: Callable[[], bool]) -> None:
    """Send ``request`` again and again and never read, until ``gone()`` or the twin
    has closed the connection (a reset on a send)."""
    client.setblocking(False)
    chunk = memoryview(request * max(1, 65536 // len(request)))
    sent = 0  # of the chunk: a send may take part of it, and the rest follows
    deadline = time.monotonic() + 30.0
    while not gone():
        assert time.monotonic() < deadline, "the twin still serves a client that never reads"
        try:
            sent = (sent + client.send(chunk[sent:])) % len(chunk)
        except BlockingIOError:
            select.select([], [client], [], 0.05)
        except OSError:
            return


def _said(caplog: pytest.LogCaptureFixture, *words: str) -> bool:
    return any(all(w in r.getMessage() for w in words) for r in caplog.records)


def test_the_tracker_twin_closes_a_client_that_never_reads(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(link_server, "WRITE_STALL_S", 0.5, raising=False)
    caplog.set_level(logging.INFO)
    with _tracker() as (server, client, address):
        wait_until(lambda: len(server.threads) == 2)  # the connection is served
        client.sendall(b"INIT\nMEAS 10000 1000\n")
        _flood(client, b"*IDN?\nSTAT?\n", lambda: len(server.threads) == 1)
        wait_until(lambda: len(server.threads) == 1)  # the accept thread alone
        assert _said(caplog, "does not read")
        # the twin serves the next client as before
        other = socket.create_connection(address, timeout=5.0)
        with other:
            other.sendall(b"*IDN?\n")
            assert other.recv(100).startswith(b"OK cellcal,mock-tracker")


def test_the_tracker_twin_drops_an_endless_line_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    with _tracker() as (server, client, _):
        for _ in range(160):  # 10 MiB without a newline
            client.sendall(b"A" * 65536)
        client.sendall(b"\n*IDN?\n")
        f = client.makefile("rb")
        assert f.readline() == b"ERR 3 BAD_PARAMETER line too long\n"
        assert f.readline().startswith(b"OK cellcal,mock-tracker")
        assert _said(caplog, "longer than")
        assert all(len(r) <= 256 for r in server.requests)


def test_the_tracker_twin_keeps_the_last_requests_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(TrackerTwin, "REQUEST_LOG", 100, raising=False)
    with _tracker() as (server, client, _):
        client.sendall(b"".join(b"STAT? %d\n" % i for i in range(250)) + b"*IDN?\n")
        f = client.makefile("rb")
        for _ in range(251):
            f.readline()
        requests = server.requests
        assert len(requests) == 100 and requests[-1] == "*IDN?"
        assert requests[0] == "STAT? 151"


def _modbus(**kw: object) -> ModbusRobotTwin:
    sim = ModbusRobotTwin(q0_deg=[0.0, -90.0, 90.0, 0.0, 45.0, 0.0], **kw)  # type: ignore[arg-type]
    sim.start(MODBUS_HOST, 0)  # listening once it returns
    return sim


def _read_holding(transaction: int, count: int = 125) -> bytes:
    return struct.pack(">HHHBBHH", transaction & 0xFFFF, 0, 6, 1, 3, 0, count)


def test_the_modbus_twin_closes_a_client_that_never_reads(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(link_server, "WRITE_STALL_S", 0.5, raising=False)
    caplog.set_level(logging.INFO)
    sim = _modbus()
    try:
        server = sim._server
        assert server is not None
        client = _stingy(sim.address)
        with client:
            wait_until(lambda: len(server.threads) == 2)  # the connection is served
            request = b"".join(_read_holding(t) for t in range(64))
            _flood(client, request, lambda: len(server.threads) == 1)
            wait_until(lambda: len(server.threads) == 1)
        assert _said(caplog, "does not read")
    finally:
        sim.stop()


def test_the_modbus_twin_keeps_the_last_requests_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ModbusRobotTwin, "REQUEST_LOG", 50, raising=False)
    sim = _modbus()
    try:
        client = socket.create_connection(sim.address, timeout=5.0)
        with client:
            client.sendall(b"".join(_read_holding(t, 2) for t in range(120)))
            got = b""
            while len(got) < 120 * 13:  # 7 header + 2 + 4 register bytes each
                got += client.recv(65536)
        requests = sim.requests  # the last 50, and up to a quarter more between trims
        assert 50 <= len(requests) <= 62 and all(r.count == 2 for r in requests)
    finally:
        sim.stop()


class _Controller:
    host = "127.0.0.144"

    def __init__(self) -> None:
        self.scripts: list[tuple[str, str]] = []

    def run_script(self, name: str, text: str) -> None:
        self.scripts.append((name, text))


def test_the_ur_script_port_drops_an_endless_line_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    ctl = _Controller()
    reader = ScriptReader(ctl)  # type: ignore[arg-type]
    for _ in range(160):  # 10 MiB without a newline
        reader.feed(b"x" * 65536)
        assert len(reader.buf) <= 70000
    assert _said(caplog, "longer than")
    reader.feed(b"\ndef prog():\n  textmsg(1)\nend\n")
    assert [name for name, _ in ctl.scripts] == ["prog"]


def test_the_ur_script_port_drops_a_program_that_never_ends(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the bound made 64 KiB (the twin's is MAX_PROGRAM): the same code path, a
    hundredth of the bytes."""
    caplog.set_level(logging.INFO)
    bound = 64 * 1024
    assert bound < MAX_PROGRAM
    monkeypatch.setattr(ur_script_port, "MAX_PROGRAM", bound)
    ctl = _Controller()
    reader = ScriptReader(ctl)  # type: ignore[arg-type]
    reader.feed(b"def endless():\n")
    for _ in range(2 * bound // 13_000 + 2):  # twice the bound, no end
        reader.feed(b"  textmsg(1)\n" * 1000)  # 13 kB
        assert reader.program is None or reader.size <= bound
    assert reader.program is None and _said(caplog, "endless")
    reader.feed(b"def prog():\n  textmsg(1)\nend\n")
    assert [name for name, _ in ctl.scripts] == ["prog"]


class _Fields:
    def getter(self, name: str) -> Callable[[], float] | None:
        return (lambda: 0.0) if name == "timestamp" else None

    def set_inputs(self, values: dict[str, object]) -> None:
        """Inputs are not what this test is about: dropped."""


def test_an_rtde_client_asking_for_endless_recipes_is_refused_not_fatal(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Recipe ids are one byte: the 256th recipe of a connection would not even encode
    (and took the twin's whole loop down with it); it is refused, and said."""
    caplog.set_level(logging.INFO)
    session = RtdeSession(1, _Fields(), {}, "127.0.0.145")  # type: ignore[arg-type]
    session.handle(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
    setup = struct.pack(">d", 125.0) + b"timestamp"
    for _ in range(300):
        (reply,) = session.handle(rtde.SETUP_OUTPUTS, setup)
    assert len(session.outputs) == 255 and reply[3] == 0  # recipe id 0: refused
    assert _said(caplog, "output recipe", "refused")
    for _ in range(300):
        (reply,) = session.handle(rtde.SETUP_INPUTS, b"input_int_register_0")
    assert len(session.inputs) == 255 and reply[3] == 0
    assert _said(caplog, "input recipe", "refused")


def test_the_ur_twin_closes_a_dashboard_client_that_never_reads() -> None:
    """Requests sent and no reply read: past a MiB of replies waiting the UR twin closes
    the connection (a reset on the client's next send) and keeps serving others."""
    from tests.mocks.test_ur_twin_wire import dashboard
    from tests.mocks.ur_clients import ur_twin

    host = "127.0.0.146"
    with ur_twin(host):
        client = socket.create_connection((host, 29999), timeout=5.0)
        with client:
            client.recv(4096)  # the greeting
            _flood(client, b"robotmode\n" * 400, lambda: False)
        assert dashboard(host, ["robotmode"])[1].startswith("Robotmode: ")
