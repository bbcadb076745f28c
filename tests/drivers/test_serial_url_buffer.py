"""``SerialUrlTransport`` over ``socket://`` reads what has arrived in chunks, not one
byte a call (pyserial's ``in_waiting`` on a socket only says whether something waits),
keeps what a caller did not ask for until its next read, and keeps line framing and
timeouts as they were: every byte once and in order, a line split across sends or
chunks whole, an unfinished line no line, nothing arrived ``b""``. Against a local
socket on 127.0.0.16x, each test with a timeout."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from cellcal.drivers.line_framing import LineReader
from cellcal.drivers.transport import CHUNK, SerialUrlTransport, TransportError

HOST = "127.0.0.161"

pytestmark = pytest.mark.timeout(30)


class Link:
    """A listening socket on HOST, the transport connected to it, and the accepted end."""

    def __init__(self) -> None:
        self.server = socket.create_server((HOST, 0))
        self.server.settimeout(10.0)
        port = self.server.getsockname()[1]
        self.transport = SerialUrlTransport(f"socket://{HOST}:{port}")
        self.peer = self.connect()

    def connect(self) -> socket.socket:
        """(Re)open the transport; the server's end of the new connection."""
        self.transport.open()
        peer, _ = self.server.accept()
        peer.settimeout(10.0)
        return peer

    def close(self) -> None:
        self.transport.close()
        self.peer.close()
        self.server.close()


@pytest.fixture
def link() -> Iterator[Link]:
    one = Link()
    try:
        yield one
    finally:
        one.close()


def test_a_burst_is_read_in_chunks_not_byte_by_byte(link: Link) -> None:
    burst = bytes(range(256)) * 12  # 3072 bytes, every value
    link.peer.sendall(burst)
    got = bytearray()
    calls = 0
    while len(got) < len(burst):
        data = link.transport.read(CHUNK, 5.0)
        assert data, "the burst stopped short"
        got += data
        calls += 1
    assert bytes(got) == burst
    assert calls <= 4, f"{calls} reads for {len(burst)} bytes"


def test_what_the_caller_did_not_ask_for_waits_for_its_next_read(link: Link) -> None:
    link.peer.sendall(b"abcdefghij")
    assert link.transport.read(4, 5.0) == b"abcd"
    assert link.transport.read(4, 5.0) == b"efgh"
    assert link.transport.read(4, 5.0) == b"ij"
    assert link.transport.read(4, 0.0) == b""  # nothing waits: no wait either
    assert link.transport.read(4, 0.2) == b""  # nothing arrives within the timeout
    link.peer.sendall(b"k")
    assert link.transport.read(4, 5.0) == b"k"


def test_lines_are_framed_as_before(link: Link) -> None:
    lines = LineReader(link.transport)
    link.peer.sendall(b"one\r\ntwo\nthr")
    assert lines.read_line(5.0).raw == b"one"  # type: ignore[union-attr]
    assert lines.read_line(5.0).raw == b"two"  # type: ignore[union-attr]
    assert lines.read_line(0.2) is None  # "thr" is no line yet
    assert lines.head == b"thr"
    link.peer.sendall(b"ee\n")
    assert lines.read_line(5.0).raw == b"three"  # type: ignore[union-attr]
    # many lines in one send, across chunk boundaries: each whole, in order
    many = [f"{k:05d} " + "x" * (k % 90) for k in range(400)]
    link.peer.sendall(b"".join(line.encode() + b"\n" for line in many))
    got = [lines.read_line(5.0) for _ in many]
    assert [g.raw.decode() for g in got if g is not None] == many
    # an overlong line is reported, not split, and the next one is whole
    link.peer.sendall(b"y" * 1000 + b"\nnext\n")
    long = lines.read_line(5.0)
    assert long is not None and long.overlong and long.size == 1001
    assert lines.read_line(5.0).raw == b"next"  # type: ignore[union-attr]


def test_bytes_before_a_drop_are_read_then_the_drop_is_said(link: Link) -> None:
    lines = LineReader(link.transport)
    link.peer.sendall(b"last\n")
    link.peer.close()
    assert lines.read_line(5.0).raw == b"last"  # type: ignore[union-attr]
    with pytest.raises(TransportError, match="connection lost"):
        lines.read_line(5.0)


def test_a_reconnect_forgets_what_the_old_link_left(link: Link) -> None:
    link.peer.sendall(b"abcdef")
    assert link.transport.read(2, 5.0) == b"ab"
    link.peer.close()
    link.peer = link.connect()
    link.peer.sendall(b"xyz")
    assert link.transport.read(CHUNK, 5.0) == b"xyz"
