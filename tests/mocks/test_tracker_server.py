"""The mock laser tracker on the wire: exact request/reply lines (PyMeasure style), the
MEAS framing and values, error codes, the line limit, STOP and BUSY, every fault, the pty
transport, and hostile input thrown at it by hypothesis.

Clients here are raw sockets and pyserial on the pty, never the tracker driver."""

from __future__ import annotations

import abc
import contextlib
import re
import socket
import time
from collections.abc import Iterator
from typing import ClassVar

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellcal.drivers.tracker_protocol import ERROR_TEXT
from cellcal.mocks import link_server
from cellcal.mocks.tracker.server import TrackerFaults, TrackerTwin

pytestmark = [pytest.mark.twin, pytest.mark.timeout(30)]

HOST = "127.0.0.5"
IDN = "OK cellcal,mock-tracker,SIM-0001,1.0"
READ_TIMEOUT = 5.0

OK_LINE = re.compile(rb"OK( [\x20-\x7e]+)?")
ERR_LINE = re.compile(rb"ERR ([0-9]+) ([A-Z_]+)( [\x20-\x7e]*)?")
EVT_LINE = re.compile(rb"EVT [A-Z_]+( [\x20-\x7e]+)?")
PT_LINE = re.compile(rb"PT ([0-9]+) (-?[0-9]+\.[0-9]{3})((?: -?[0-9]+\.[0-9]{4}){3})")
END_LINE = re.compile(rb"END ([0-9]+)")


def is_protocol_line(raw: bytes) -> bool:
    return any(p.fullmatch(raw) for p in (OK_LINE, ERR_LINE, EVT_LINE, PT_LINE, END_LINE))


def is_reply(raw: bytes) -> bool:
    """A well-formed OK/ERR line with an error code and TEXT from the spec's table."""
    if OK_LINE.fullmatch(raw):
        return True
    m = ERR_LINE.fullmatch(raw)
    return m is not None and ERROR_TEXT.get(int(m.group(1))) == m.group(2).decode()


# ---------------------------------------------------------------------------- doubles


class RampSource:
    """Known points: row k of the whole run is (1000 + k, -50 - 0.5 k, 875.0770 + 0.0001 k)."""

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.k = 0

    def row(self, k: int) -> tuple[float, float, float]:
        return 1000.0 + k, -50.0 - 0.5 * k, 875.0770 + 0.0001 * k

    def sample(self, n: int) -> np.ndarray:
        self.calls.append(n)
        rows = np.array([self.row(k) for k in range(self.k, self.k + n)])
        self.k += n
        return rows


class TableSource:
    def __init__(self, xyz: list[list[float]]) -> None:
        self.xyz = np.array(xyz)

    def sample(self, n: int) -> np.ndarray:
        return self.xyz[:n]


class BrokenSource:
    def __init__(self, how: str) -> None:
        self.how = how

    def sample(self, n: int) -> np.ndarray:
        if self.how == "raise":
            raise RuntimeError("simulation failed")
        if self.how == "shape":
            return np.zeros((n, 2))
        return np.full((n, 3), np.nan)


# ---------------------------------------------------------------------------- clients


class Client(abc.ABC):
    """Line-oriented client; subclasses move the bytes."""

    opened: ClassVar[list[Client]] = []  # closed after each test

    def __init__(self) -> None:
        self.buf = bytearray()
        Client.opened.append(self)

    @abc.abstractmethod
    def _recv(self, timeout: float) -> bytes:
        """What arrives within ``timeout`` s (b"" when nothing does)."""

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of ``data``."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the link."""

    def send(self, line: str | bytes) -> None:
        self.write((line.encode() if isinstance(line, str) else line) + b"\n")

    def raw_line(self, timeout: float = READ_TIMEOUT) -> bytes:
        deadline = time.monotonic() + timeout
        while (nl := self.buf.find(b"\n")) < 0:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no complete line within {timeout} s; have {bytes(self.buf)!r}")
            data = self._recv(left)
            if data == b"":
                raise EOFError(f"closed; have {bytes(self.buf)!r}")
            self.buf += data
        line = bytes(self.buf[:nl])
        del self.buf[: nl + 1]
        return line

    def line(self, timeout: float = READ_TIMEOUT) -> str:
        raw = self.raw_line(timeout)
        assert is_protocol_line(raw), raw
        return raw.decode("ascii")

    def lines(self, k: int) -> list[str]:
        return [self.line() for _ in range(k)]

    def ask(self, request: str | bytes, replies: int = 1) -> list[str]:
        self.send(request)
        return self.lines(replies)

    def series(self) -> tuple[list[str], str]:
        """The PT lines of a series (events skipped) and the line that ended it."""
        points = []
        while (line := self.line()).startswith(("PT ", "EVT ")):
            if line.startswith("PT "):
                points.append(line)
        return points, line

    def silent(self, timeout: float) -> bool:
        """True if no line arrives within ``timeout`` seconds."""
        try:
            self.raw_line(timeout)
        except TimeoutError:
            return True
        return False


class TcpClient(Client):
    def __init__(self, addr: tuple[str, int]) -> None:
        super().__init__()
        self.sock = socket.create_connection(addr, timeout=READ_TIMEOUT)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def _recv(self, timeout: float) -> bytes:
        self.sock.settimeout(timeout)
        return self.sock.recv(65536)  # TimeoutError when nothing came

    def raw_line(self, timeout: float = READ_TIMEOUT) -> bytes:
        try:
            return super().raw_line(timeout)
        except ConnectionResetError as exc:
            raise EOFError("reset") from exc

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)

    def close(self) -> None:
        self.sock.close()

    def at_eof(self) -> bool:
        """True if the server closed the connection with no further line."""
        try:
            self.raw_line()
        except EOFError:
            return not self.buf
        return False

    def lines_until_eof(self) -> int:
        count = 0
        while True:
            try:
                self.raw_line()
            except EOFError:
                return count
            count += 1


class PtyClient(Client):
    def __init__(self, path: str) -> None:
        super().__init__()
        self.port = serial.Serial(path, baudrate=115200, timeout=0.05)

    def _recv(self, timeout: float) -> bytes:
        deadline = time.monotonic() + timeout
        while True:
            data = bytes(self.port.read(max(1, self.port.in_waiting)))
            if data:
                return data
            if time.monotonic() >= deadline:
                raise TimeoutError

    def write(self, data: bytes) -> None:
        self.port.write(data)
        self.port.flush()

    def close(self) -> None:
        self.port.close()


@pytest.fixture(autouse=True)
def _close_clients() -> Iterator[None]:
    yield
    while Client.opened:
        with contextlib.suppress(OSError, serial.SerialException):
            Client.opened.pop().close()


@pytest.fixture
def serve() -> Iterator:
    """``serve(source=None, **kwargs)`` → (tracker, TCP address); stopped at teardown."""
    started: list[TrackerTwin] = []

    def start(source=None, **kwargs):
        tracker = TrackerTwin(source or RampSource(), **kwargs)
        started.append(tracker)
        return tracker, tracker.start_tcp(HOST, 0)

    yield start
    for tracker in started:
        tracker.stop()


def converse(client: Client, pairs, idn: str = IDN) -> None:
    """Each request gets exactly its expected lines, and nothing else follows."""
    for request, expected in pairs:
        assert client.ask(request, len(expected)) == expected, request
    assert client.ask("*IDN?") == [idn]


# ---------------------------------------------------------------------------- requests

ENV_RANGE_ERRORS = [
    "ENV T=40.01 P=1013 RH=45",
    "ENV T=-0.5 P=1013 RH=45",
    "ENV T=20 P=599.9 RH=45",
    "ENV T=20 P=1100.5 RH=45",
    "ENV T=20 P=1013 RH=95.1",
    "ENV T=20 P=1013 RH=-1",
]
ENV_MALFORMED = [
    "ENV",
    "ENV T=20",
    "ENV T=20 P=1000",
    "ENV T=abc P=1000 RH=50",
    "ENV T= P=1000 RH=50",
    "ENV T=20 P=1000 RH=50 X=1",
    "ENV T=20 T=21 P=1000",
    "ENV T=nan P=1000 RH=50",
    "ENV T=inf P=1000 RH=50",
    "ENV T=20 P=1000 H=50",
    "ENV 20 1000 50",
]
MEAS_MALFORMED = [
    "MEAS",
    "MEAS 0",
    "MEAS 10001",
    "MEAS -3",
    "MEAS 3.5",
    "MEAS abc",
    "MEAS 3 0",
    "MEAS 3 -10",
    "MEAS 3 1000.5",
    "MEAS 3 fast",
    "MEAS 3 nan",
    "MEAS 3 10 4",
]

CONVERSATIONS = {
    "idn": [("*IDN?", [IDN])],
    "crlf": [("*IDN?\r", [IDN]), ("STAT?\r", ["OK ready=0 beam=1 meteo=1 init=0"])],
    "init-and-status": [
        ("STAT?", ["OK ready=0 beam=1 meteo=1 init=0"]),
        ("INIT", ["OK"]),
        ("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"]),
        ("INIT", ["OK"]),
    ],
    "environment": [
        ("ENV?", ["OK T=20.0 P=1013.25 RH=45.0"]),
        ("ENV T=21.5 P=1000 RH=50", ["OK"]),
        ("ENV?", ["OK T=21.5 P=1000.0 RH=50.0"]),
        ("ENV RH=12.25 T=19.125 P=998.5", ["OK"]),
        ("ENV?", ["OK T=19.125 P=998.5 RH=12.25"]),
        ("ENV T=0 P=600 RH=0", ["OK"]),
        ("ENV T=40 P=1100 RH=95", ["OK"]),
        ("ENV T=2.5e1 P=1.0e3 RH=5E1", ["OK"]),
        ("ENV?", ["OK T=25.0 P=1000.0 RH=50.0"]),
    ],
    "environment-out-of-range": [
        *[(r, ["ERR 57 METEO_OUT_OF_RANGE"]) for r in ENV_RANGE_ERRORS],
        ("ENV?", ["OK T=20.0 P=1013.25 RH=45.0"]),
    ],
    "environment-malformed": [
        *[(r, ["ERR 3 BAD_PARAMETER"]) for r in ENV_MALFORMED],
        ("ENV?", ["OK T=20.0 P=1013.25 RH=45.0"]),
    ],
    "reflector": [
        ("SMR?", ["OK RRR15"]),
        ("SMR RRR05", ["OK"]),
        ("SMR?", ["OK RRR05"]),
        ("SMR RRR0875", ["OK"]),
        ("SMR TBR05", ["OK"]),
        ("SMR?", ["OK TBR05"]),
        ("SMR RRR15", ["OK"]),
        ("SMR XYZ", ["ERR 3 BAD_PARAMETER"]),
        ("SMR rrr15", ["ERR 3 BAD_PARAMETER"]),
        ("SMR", ["ERR 3 BAD_PARAMETER"]),
        ("SMR RRR05 RRR15", ["ERR 3 BAD_PARAMETER"]),
        ("SMR?", ["OK RRR15"]),
    ],
    "meas-before-init": [
        ("MEAS 3", ["ERR 39 NOT_INITIALIZED"]),
        ("MEAS 3 100", ["ERR 39 NOT_INITIALIZED"]),
    ],
    "meas-malformed": [
        ("INIT", ["OK"]),
        *[(r, ["ERR 3 BAD_PARAMETER"]) for r in MEAS_MALFORMED],
    ],
    "stop-when-idle": [("STOP", ["OK"])],
    "unknown": [
        ("FOO", ["ERR 4 UNKNOWN_COMMAND"]),
        ("*idn?", ["ERR 4 UNKNOWN_COMMAND"]),
        ("MEASURE 3", ["ERR 4 UNKNOWN_COMMAND"]),
        ("OK", ["ERR 4 UNKNOWN_COMMAND"]),
        (b"\xff\xfe\x00", ["ERR 4 UNKNOWN_COMMAND"]),
        (b"INIT\x00", ["ERR 4 UNKNOWN_COMMAND"]),
    ],
    "arguments-where-none-belong": [
        ("*IDN? now", ["ERR 3 BAD_PARAMETER"]),
        ("INIT 1", ["ERR 3 BAD_PARAMETER"]),
        ("STAT? x", ["ERR 3 BAD_PARAMETER"]),
        ("ENV? T", ["ERR 3 BAD_PARAMETER"]),
        ("SMR? RRR15", ["ERR 3 BAD_PARAMETER"]),
        ("STOP now", ["ERR 3 BAD_PARAMETER"]),
        (b"MEAS 3\x01", ["ERR 3 BAD_PARAMETER"]),
        (b"SMR RRR15\xc3\xa9", ["ERR 3 BAD_PARAMETER"]),
    ],
    "blank-lines-ignored": [("", []), ("\r", []), ("   \t ", []), ("*IDN?", [IDN])],
    "whitespace-between-words": [("  SMR \t RRR05  ", ["OK"]), ("SMR?", ["OK RRR05"])],
}


@pytest.mark.parametrize("name", sorted(CONVERSATIONS))
def test_request_reply_pairs_on_the_wire(serve, name: str) -> None:
    _, addr = serve()
    client = TcpClient(addr)
    converse(client, CONVERSATIONS[name])


def test_serial_number_and_requests_record(serve) -> None:
    tracker, addr = serve(serial="LT-42")
    client = TcpClient(addr)
    idn = "OK cellcal,mock-tracker,LT-42,1.0"
    converse(client, [("*IDN?", [idn]), ("", []), ("INIT\r", ["OK"])], idn=idn)
    assert tracker.requests == ["*IDN?", "INIT", "*IDN?"]


# ---------------------------------------------------------------------------- MEAS


def test_meas_framing_matches_the_spec_example(serve) -> None:
    source = TableSource([[1048.62012, 29.94401, 875.07699], [1048.6199, 29.9442, 875.0768]])
    _, addr = serve(source)
    converse(
        TcpClient(addr),
        [
            ("INIT", ["OK"]),
            (
                "MEAS 2",
                [
                    "OK 2",
                    "PT 0 12.100 1048.6201 29.9440 875.0770",
                    "PT 1 12.200 1048.6199 29.9442 875.0768",
                    "END 2",
                ],
            ),
        ],
    )


def test_meas_values_clock_and_one_sample_call_per_series(serve) -> None:
    source = RampSource()
    tracker, addr = serve(source, clock_start=100.0)
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    k = 0
    clock = 100.0
    for n, rate in ((5, None), (3, 100.0), (4, 0.5), (1, 1000.0)):
        request = f"MEAS {n}" if rate is None else f"MEAS {n} {rate:g}"
        assert client.ask(request) == [f"OK {n}"]
        points, last = client.series()
        assert last == f"END {n}"
        assert len(points) == n
        step = 1.0 / (rate or 10.0)
        for i, line in enumerate(points):
            m = PT_LINE.fullmatch(line.encode())
            assert m is not None
            assert int(m.group(1)) == i
            assert m.group(2).decode() == f"{clock + (i + 1) * step:.3f}"
            xyz = [float(v) for v in m.group(3).split()]
            np.testing.assert_allclose(xyz, source.row(k), atol=5e-5, rtol=0)
            k += 1
        clock += n * step
    assert source.calls == [5, 3, 4, 1]
    assert tracker.requests[-1] == "MEAS 1 1000"


def test_meas_largest_series_at_the_highest_rate(serve) -> None:
    _, addr = serve()
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    assert client.ask("MEAS 10000 1000") == ["OK 10000"]
    points, last = client.series()
    assert last == "END 10000"
    t = np.array([float(p.split()[2]) for p in points])
    assert [int(p.split()[1]) for p in points] == list(range(10000))
    assert np.all(np.diff(t) > 0)
    assert points[-1].split()[2] == "22.000"


def test_paced_series_takes_wall_time(serve) -> None:
    _, addr = serve(time_scale=0.2)  # 10 Hz → 20 ms of wall time between points
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    start = time.monotonic()
    assert client.ask("MEAS 6") == ["OK 6"]
    points, last = client.series()
    assert (len(points), last) == (6, "END 6")
    assert time.monotonic() - start >= 5 * 0.02


def test_stop_during_a_paced_series_ends_it_with_end_k(serve) -> None:
    tracker, addr = serve(time_scale=1.0)  # 1000 Hz → 1 ms between points: 10 s in all
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    assert client.ask("MEAS 10000 1000") == ["OK 10000"]
    seen = client.lines(3)
    client.send("STOP")
    while not (line := client.line()).startswith("END"):
        seen.append(line)
    assert seen[-1] == "OK"
    points = seen[:-1]
    k = int(line.split()[1])
    assert 3 <= k < 10000
    assert points == [p for p in points if p.startswith("PT ")]
    assert [int(p.split()[1]) for p in points] == list(range(k))
    converse(client, [("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"])])
    assert client.ask("MEAS 2") == ["OK 2"]
    assert client.series()[1] == "END 2"
    assert tracker.requests == ["INIT", "MEAS 10000 1000", "STOP", "STAT?", "*IDN?", "MEAS 2"]


def test_busy_while_a_series_runs_on_this_or_another_connection(serve) -> None:
    _, addr = serve(time_scale=1.0)
    client, other = TcpClient(addr), TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    assert client.ask("MEAS 10000 1000") == ["OK 10000"]
    client.line()
    replies = []
    for request in ("MEAS 5", "INIT", "STAT?", "*IDN?", "STOP"):
        client.send(request)
        line = client.line()
        while line.startswith("PT "):  # the running series' points come first
            line = client.line()
        replies.append(line)
    assert replies == ["ERR 1 BUSY", "ERR 1 BUSY", "OK ready=0 beam=1 meteo=1 init=1", IDN, "OK"]
    assert client.line().startswith("END ")
    # Again, with the second client asking while the first measures.
    assert client.ask("MEAS 10000 1000") == ["OK 10000"]
    client.line()
    assert other.ask("MEAS 5") == ["ERR 1 BUSY"]
    assert other.ask("STAT?") == ["OK ready=0 beam=1 meteo=1 init=1"]
    client.send("STOP")
    while not client.line().startswith("END "):
        pass
    assert other.ask("MEAS 1") == ["OK 1"]
    assert other.series()[1] == "END 1"


@pytest.mark.parametrize("how", ["raise", "shape", "nan"])
def test_a_failing_target_source_gives_err_38_and_the_server_carries_on(serve, how) -> None:
    _, addr = serve(BrokenSource(how))
    converse(
        TcpClient(addr),
        [
            ("INIT", ["OK"]),
            ("MEAS 3", ["ERR 38 NO_TRACKER target source failed"]),
            ("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"]),
        ],
    )


# ---------------------------------------------------------------------------- line limit


def test_line_limit_is_256_bytes(serve) -> None:
    tracker, addr = serve()
    client = TcpClient(addr)
    converse(
        client,
        [
            (b"A" * 256, ["ERR 4 UNKNOWN_COMMAND"]),
            (b"A" * 256 + b"\r", ["ERR 4 UNKNOWN_COMMAND"]),
            (b"SMR RRR05" + b" " * 247, ["OK"]),
            (b"A" * 257, ["ERR 3 BAD_PARAMETER line too long"]),
            (b"*IDN?" + b" " * 252, ["ERR 3 BAD_PARAMETER line too long"]),
            (b"\xff" * 300 + b"\r", ["ERR 3 BAD_PARAMETER line too long"]),
        ],
    )
    # A huge line in pieces: one reply, and the bytes after its "\n" are a new line.
    client.write(b"B" * 100_000)
    client.write(b"C" * 100_000 + b"\n*IDN?\n")
    assert client.lines(2) == ["ERR 3 BAD_PARAMETER line too long", IDN]
    assert tracker.requests[-2] == "B" * 256


# ---------------------------------------------------------------------------- faults


def test_beam_breaks_after_k_points_for_the_configured_series(serve) -> None:
    faults = TrackerFaults(beam_break_after=3, beam_breaks=2)
    tracker, addr = serve(faults=faults)
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    for _ in range(2):
        assert client.ask("MEAS 10") == ["OK 10"]
        points = client.lines(3)
        assert [p.split()[1] for p in points] == ["0", "1", "2"]
        assert client.lines(3) == ["EVT BEAM LOST", "ERR 40 BEAM_BROKEN", "EVT BEAM OK"]
    assert client.ask("MEAS 10") == ["OK 10"]
    points, last = client.series()
    assert (len(points), last) == (10, "END 10")
    # The clock moved by the points sent: 3 + 3 + 10 at 10 Hz after 12.0.
    assert points[-1].split()[2] == "13.600"
    assert tracker.events_sent == 4
    converse(client, [("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"])])


def test_beam_breaks_half_way_through_every_nth_series(serve) -> None:
    """The soak's fault: every 3rd series loses the beam after half its points."""
    _, addr = serve(faults=TrackerFaults(beam_break_every=3))
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    ends = []
    for _ in range(6):
        assert client.ask("MEAS 6") == ["OK 6"]
        lines = client.lines(4)
        # a whole series: 6 points and END; a broken one: 3 points and the beam's lines
        lines += client.lines(3 if lines[-1].startswith("PT") else 2)
        ends.append(" | ".join(lines[3:]) if lines[-1] == "EVT BEAM OK" else lines[-1])
    broken = "EVT BEAM LOST | ERR 40 BEAM_BROKEN | EVT BEAM OK"
    assert ends == ["END 6", "END 6", broken, "END 6", "END 6", broken]


def test_beam_break_at_zero_points_and_a_pending_break(serve) -> None:
    _, addr = serve(faults=TrackerFaults(beam_break_after=0))
    converse(
        TcpClient(addr),
        [
            ("INIT", ["OK"]),
            ("MEAS 2", ["OK 2", "EVT BEAM LOST", "ERR 40 BEAM_BROKEN", "EVT BEAM OK"]),
            # The source gave two rows for the broken series; none of them was sent.
            ("MEAS 1", ["OK 1", "PT 0 12.100 1002.0000 -51.0000 875.0772", "END 1"]),
        ],
    )
    # A series no longer than beam_break_after completes; the break waits for a longer one.
    _, addr = serve(faults=TrackerFaults(beam_break_after=2))
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    assert client.ask("MEAS 2", 4)[-1] == "END 2"
    assert client.ask("MEAS 5", 6)[-3:] == ["EVT BEAM LOST", "ERR 40 BEAM_BROKEN", "EVT BEAM OK"]


def test_beam_restores_after_the_configured_time_with_evt_beam_ok(serve) -> None:
    restore = 0.5
    _, addr = serve(faults=TrackerFaults(beam_break_after=1, beam_restore_s=restore))
    client = TcpClient(addr)
    assert client.ask("INIT") == ["OK"]
    assert client.ask("MEAS 4", 4)[1:] == [
        "PT 0 12.100 1000.0000 -50.0000 875.0770",
        "EVT BEAM LOST",
        "ERR 40 BEAM_BROKEN",
    ]
    broken_at = time.monotonic()
    assert client.ask("STAT?") == ["OK ready=0 beam=0 meteo=1 init=1"]
    assert client.ask("MEAS 4") == ["ERR 40 BEAM_BROKEN"]
    assert client.line() == "EVT BEAM OK"  # a read with a timeout, not a sleep
    assert time.monotonic() - broken_at >= restore - 0.05
    assert client.ask("STAT?") == ["OK ready=1 beam=1 meteo=1 init=1"]
    assert client.ask("MEAS 4", 6)[-1] == "END 4"


def test_init_restores_the_beam(serve) -> None:
    tracker, addr = serve(faults=TrackerFaults(beam_break_after=0, beam_restore_s=60.0))
    converse(
        TcpClient(addr),
        [
            ("INIT", ["OK"]),
            ("MEAS 3", ["OK 3", "EVT BEAM LOST", "ERR 40 BEAM_BROKEN"]),
            ("STAT?", ["OK ready=0 beam=0 meteo=1 init=1"]),
            ("INIT", ["OK", "EVT BEAM OK"]),
            ("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"]),
        ],
    )
    assert tracker.events_sent == 2


def read_with_garbage(client: TcpClient, protocol_lines: int) -> list[bytes]:
    out: list[bytes] = []
    while sum(map(is_protocol_line, out)) < protocol_lines:
        out.append(client.raw_line())
    return out


def garbage_positions_ok(stream: list[bytes], every: int) -> int:
    """Assert a garbage line precedes exactly every ``every``-th protocol line."""
    count = 0
    garbage = 0
    for prev, raw in zip([b"OK", *stream], stream, strict=False):
        if is_protocol_line(raw):
            count += 1
            assert (not is_protocol_line(prev)) == (count % every == 0), (count, prev, raw)
        else:
            garbage += 1
            assert is_protocol_line(prev) or garbage == 1
    return garbage


def test_garbage_lines_at_the_configured_cadence(serve) -> None:
    streams = []
    for seed in (7, 7, 8):
        _, addr = serve(faults=TrackerFaults(garbage_every=3, seed=seed))
        client = TcpClient(addr)
        client.send("INIT")
        client.send("MEAS 60")  # protocol lines: OK, OK 60, 60 PT, END 60 = 63
        stream = read_with_garbage(client, 63)
        assert garbage_positions_ok(stream, 3) == 21
        streams.append(stream)
        client.send("*IDN?")
        assert read_with_garbage(client, 1)[-1].decode() == IDN
    assert streams[0] == streams[1]  # the same seed, the same garbage
    assert streams[0] != streams[2]
    junk = [raw for s in streams for raw in s if not is_protocol_line(raw)]
    assert any(raw.startswith(b"PT") for raw in junk)
    assert any(any(b > 0x7F for b in raw) for raw in junk)
    assert all(b"\n" not in raw for raw in junk)


def test_events_precede_every_kth_reply(serve) -> None:
    tracker, addr = serve(faults=TrackerFaults(event_every=2))
    client = TcpClient(addr)
    lines = []
    for request in ("*IDN?", "*IDN?", "INIT", "SMR?", "MEAS 1", "BAD"):
        client.send(request)
        lines.append(client.line())
        if lines[-1].startswith("EVT"):
            lines.append(client.line())
        if request == "MEAS 1":
            lines += client.lines(2)
    temps = [line for line in lines if line.startswith("EVT")]
    assert len(temps) == 3 == tracker.events_sent
    assert all(re.fullmatch(r"EVT TEMP \d+\.\d", t) for t in temps)
    assert abs(float(temps[0].split()[2]) - 20.0) < 0.5
    replies = [line for line in lines if not line.startswith("EVT")]
    assert replies[:4] == [IDN, IDN, "OK", "OK RRR15"]
    assert replies[4:] == [
        "OK 1",
        "PT 0 12.100 1000.0000 -50.0000 875.0770",
        "END 1",
        "ERR 4 UNKNOWN_COMMAND",
    ]
    assert [i for i, line in enumerate(lines) if line.startswith("EVT")] == [1, 4, 9]


def test_reply_delay_slows_every_reply(serve) -> None:
    delay = 0.1
    _, addr = serve(faults=TrackerFaults(reply_delay_s=delay))
    client = TcpClient(addr)
    start = time.monotonic()
    assert client.ask("*IDN?") == [IDN]
    assert client.ask("FOO") == ["ERR 4 UNKNOWN_COMMAND"]
    assert time.monotonic() - start >= 2 * delay - 0.01


def test_dropped_connection_then_reconnect_works(serve) -> None:
    tracker, addr = serve(faults=TrackerFaults(drop_after_lines=4))
    first = TcpClient(addr)
    assert first.ask("*IDN?") == [IDN]
    assert first.ask("INIT") == ["OK"]
    assert first.ask("MEAS 5", 2) == ["OK 5", "PT 0 12.100 1000.0000 -50.0000 875.0770"]
    assert first.at_eof()
    # The tracker kept its state; the series is no longer running; the count restarts.
    second = TcpClient(addr)
    assert second.ask("STAT?") == ["OK ready=1 beam=1 meteo=1 init=1"]
    assert second.ask("MEAS 1", 3) == ["OK 1", "PT 0 12.200 1005.0000 -52.5000 875.0775", "END 1"]
    assert second.at_eof()
    third = TcpClient(addr)
    assert third.ask("*IDN?") == [IDN]
    assert tracker.connections == 3


def test_drop_after_zero_lines_closes_at_once(serve) -> None:
    _, addr = serve(faults=TrackerFaults(drop_after_lines=0))
    client = TcpClient(addr)
    client.send("*IDN?")
    assert client.at_eof()


def test_clients_one_after_another_share_the_tracker_state(serve) -> None:
    tracker, addr = serve()
    for i in range(3):
        client = TcpClient(addr)
        expect_init = "1" if i else "0"
        assert client.ask("STAT?") == [f"OK ready={expect_init} beam=1 meteo=1 init={expect_init}"]
        assert client.ask("INIT") == ["OK"]
        client.close()
    assert tracker.connections == 3


# ---------------------------------------------------------------------------- pty


@pytest.mark.parametrize("watch", ["inotify", "hang-up"])
def test_pty_transport_serves_the_same_exchange(monkeypatch, watch: str) -> None:
    if watch == "hang-up":  # where there is no inotify, a client's close is a hang-up
        monkeypatch.setattr(link_server, "_inotify_watch", lambda path: None)
    source = TableSource([[1048.62012, 29.94401, 875.07699], [1048.6199, 29.9442, 875.0768]])
    with TrackerTwin(source) as tracker:
        path = tracker.start_pty()
        assert path.startswith("/dev/")
        client = PtyClient(path)
        converse(
            client,
            [
                ("*IDN?", [IDN]),
                ("STAT?\r", ["OK ready=0 beam=1 meteo=1 init=0"]),
                ("MEAS 2", ["ERR 39 NOT_INITIALIZED"]),
                ("INIT", ["OK"]),
                (
                    "MEAS 2",
                    [
                        "OK 2",
                        "PT 0 12.100 1048.6201 29.9440 875.0770",
                        "PT 1 12.200 1048.6199 29.9442 875.0768",
                        "END 2",
                    ],
                ),
                (b"A" * 300, ["ERR 3 BAD_PARAMETER line too long"]),
                (b"\xff\x00\x1b[2J", ["ERR 4 UNKNOWN_COMMAND"]),
            ],
        )
        client.close()
        again = PtyClient(path)
        converse(again, [("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"])])
        again.close()
        if watch == "inotify":
            assert tracker.connections == 2


def test_pty_large_series_flows_through() -> None:
    with TrackerTwin(RampSource()) as tracker:
        client = PtyClient(tracker.start_pty())
        assert client.ask("INIT") == ["OK"]
        assert client.ask("MEAS 5000 1000") == ["OK 5000"]
        points, last = client.series()
        assert (len(points), last) == (5000, "END 5000")
        client.close()


def test_pty_drop_stops_answering_until_reopened() -> None:
    with TrackerTwin(RampSource(), faults=TrackerFaults(drop_after_lines=2)) as tracker:
        path = tracker.start_pty()
        client = PtyClient(path)
        assert client.ask("*IDN?") == [IDN]
        assert client.ask("INIT") == ["OK"]
        client.send("STAT?")
        assert client.silent(0.3)
        client.close()
        again = PtyClient(path)  # at once: a close and a reopen are never missed
        assert again.ask("*IDN?") == [IDN]
        assert again.ask("STAT?") == ["OK ready=1 beam=1 meteo=1 init=1"]
        again.send("STAT?")
        assert again.silent(0.3)
        again.close()
        third = PtyClient(path)
        assert third.ask("*IDN?") == [IDN]
        third.close()
        assert tracker.connections == 3


# ---------------------------------------------------------------------------- lifecycle


def test_stop_closes_everything_and_is_idempotent() -> None:
    tracker = TrackerTwin(RampSource(), time_scale=1.0)
    with tracker:
        addr = tracker.start_tcp("127.0.0.6", 0)
        assert addr[0] == "127.0.0.6"
        tracker.start_pty()
        client = TcpClient(addr)
        assert client.ask("INIT") == ["OK"]
        assert client.ask("MEAS 10000 10") == ["OK 10000"]  # 1000 s of streaming
    assert client.lines_until_eof() < 10000
    tracker.stop()
    # This tracker's threads are all gone (other tests' trackers may still be winding down).
    assert [t.name for t in tracker.threads] == []
    with pytest.raises(OSError):
        socket.create_connection(addr, timeout=1.0)
    with pytest.raises(RuntimeError):
        tracker.start_tcp("127.0.0.6", 0)


def test_bad_construction_is_refused() -> None:
    for serial_number in ("A B", "A,B", "", "Sé"):
        with pytest.raises(ValueError):
            TrackerTwin(RampSource(), serial=serial_number)
    with pytest.raises(ValueError):
        TrackerTwin(RampSource(), time_scale=-1.0)
    for bad in (
        {"garbage_every": -1},
        {"beam_break_after": -1},
        {"reply_delay_s": float("nan")},
        {"drop_after_lines": -2},
    ):
        with pytest.raises(ValueError):
            TrackerFaults(**bad)


# ---------------------------------------------------------------------------- hostile input

COMMAND_WORDS = [b"*IDN?", b"INIT", b"STAT?", b"ENV?", b"ENV", b"SMR", b"SMR?", b"MEAS", b"STOP"]
ARG_WORDS = [
    b"T=20",
    b"P=1000",
    b"RH=50",
    b"T=99",
    b"RRR15",
    b"TBR05",
    b"1",
    b"3",
    b"10000",
    b"0",
    b"-1",
    b"1e3",
    b"nan",
    b"1000",
    b"0.5",
]
NO_NL = st.binary(max_size=300).map(lambda b: b.replace(b"\n", b""))
ARG = st.one_of(
    st.sampled_from(ARG_WORDS + COMMAND_WORDS),
    st.binary(max_size=6).map(lambda b: b.replace(b"\n", b"")),
)
HOSTILE_LINE = st.one_of(
    NO_NL,
    st.tuples(st.sampled_from(COMMAND_WORDS), st.lists(ARG, max_size=4)).map(
        lambda c: b" ".join([c[0], *c[1]])
    ),
    st.lists(ARG, max_size=5).map(b" ".join),
    st.integers(200, 3000).map(lambda k: b"\x85" * k),
)


def test_hostile_lines_get_one_well_formed_reply_each_and_the_server_keeps_serving() -> None:
    with TrackerTwin(RampSource()) as tracker:
        client = TcpClient(tracker.start_tcp("127.0.0.7", 0))
        tried: list[bytes] = []
        assert client.ask("INIT") == ["OK"]  # so that a MEAS may stream a series

        @settings(
            max_examples=150,
            deadline=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        )
        @given(line=HOSTILE_LINE, cut=st.integers(0, 3000))
        def check(line: bytes, cut: int) -> None:
            tried.append(line)
            client.write(line[:cut])
            client.write(line[cut:] + b"\n")
            content = line[:-1] if line.endswith(b"\r") else line
            if len(content) > 256:
                assert client.raw_line() == b"ERR 3 BAD_PARAMETER line too long"
            elif content.split():
                reply = client.raw_line()
                assert is_reply(reply), (line, reply)
                assert not reply.startswith(b"ERR 38"), (line, reply)
                if content.split()[0] == b"MEAS" and reply.startswith(b"OK "):
                    n = int(reply.split()[1])
                    for i in range(n):
                        m = PT_LINE.fullmatch(client.raw_line())
                        assert m is not None and int(m.group(1)) == i
                    assert client.raw_line() == f"END {n}".encode()
            client.send("*IDN?")
            assert client.raw_line().decode() == IDN

        check()
        assert len(tried) >= 100
        assert tracker.connections == 1
