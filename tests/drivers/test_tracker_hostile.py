"""The tracker driver against hostile trackers (issue 29): every wait is bounded, an empty
or malformed measurement block is one DeviceError line, and a device that talks but not
the protocol is said to be so — with what it sent — never "unreachable"."""

from __future__ import annotations

import contextlib
import random
import socket
import threading
from collections.abc import Callable, Iterator

import pytest

from cellcal.drivers.tracker import LineTracker
from cellcal.errors import DeviceError
from tests.drivers.scripted import ScriptedTransport

HOST = "127.0.0.141"


class Answering(ScriptedTransport):
    """A tracker that answers every request at once, ``measure(request)`` giving the
    lines that answer a MEAS; ``stream`` lines, if any, come one per read, for ever."""

    def __init__(self, measure: Callable[[str], list[str]], stream: str | None = None) -> None:
        super().__init__([])
        self.measure = measure
        self.stream = stream

    def write(self, data: bytes) -> None:
        line = data.decode("ascii").rstrip("\n")
        self.written.append(line)
        if line == "*IDN?":
            replies = ["OK Acme,T1,SN-1,1.0"]
        elif line.startswith("MEAS"):
            replies = self.measure(line)
        else:
            replies = ["OK ready=1 beam=1 meteo=1 init=1" if line == "STAT?" else "OK"]
        self._out += "".join(r + "\n" for r in replies).encode()

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self.stream is not None and not self._out and self.written[-1].startswith("MEAS"):
            return (self.stream + "\n").encode()
        return super().read(max_bytes, timeout)


def _tracker(transport: ScriptedTransport, **kw: object) -> LineTracker:
    lt = LineTracker(
        "tracker", "scripted://", transport=transport, timeout=0.2, backoff_s=0.0, **kw
    )
    lt.connect()
    return lt


def _one_line(exc: BaseException) -> str:
    text = str(exc)
    assert "\n" not in text and text, text
    return text


@pytest.mark.timeout(30)
def test_a_tracker_answering_end_0_is_one_error_at_once() -> None:
    t = Answering(lambda req: [f"OK {req.split()[1]}", "END 0"])
    lt = _tracker(t)
    with pytest.raises(DeviceError) as info:
        lt.measure(10000, 1000.0)
    text = _one_line(info.value)
    assert "empty" in text and "END 0" in text, text
    # not 2 n = 20000 series asked for, each answered with nothing
    assert sum(w.startswith("MEAS") for w in t.written) <= 2, len(t.written)


@pytest.mark.timeout(30)
def test_an_empty_series_after_points_kept_ends_the_re_takes() -> None:
    answers = iter(
        [
            ["OK 5", "PT 0 1.0 1 1 1", "PT 1 1.1 2 2 2", "EVT BEAM LOST", "ERR 40 BEAM_BROKEN"],
            ["OK 3", "END 0"],
        ]
    )
    t = Answering(lambda req: next(answers, None) or [f"OK {req.split()[1]}", "END 0"])
    lt = _tracker(t)
    s = lt.measure(5, 10.0)
    assert s.n == 2
    assert "series ended after 0 of 3 points" in s.note
    assert sum(w.startswith("MEAS") for w in t.written) == 2


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    "stream",
    ["PT 7 1.0 1 1 1", "PT 0 1.0 1 1", "garbage \x01\x02", "EVT TEMP 20.0"],
    ids=["points out of order", "short points", "garbage", "events only"],
)
def test_a_block_that_never_ends_is_one_error_without_reconnecting(stream: str) -> None:
    t = Answering(lambda req: [f"OK {req.split()[1]}"], stream=stream)
    lt = _tracker(t, reconnects=3)
    with pytest.raises(DeviceError) as info:
        lt.measure(3, 1000.0)
    text = _one_line(info.value)
    assert "MEAS 3" in text or "series" in text, text
    assert lt.reconnections == 0, text  # the link is up: reconnecting would not help
    assert sum(w.startswith("MEAS") for w in t.written) == 1


# -- garbage before a reply, over TCP -------------------------------------------------


@contextlib.contextmanager
def _talker(garbage: bytes) -> Iterator[str]:
    """A TCP tracker that answers every request, after ``garbage`` before its first
    answer on each connection; its URL once listening."""
    listener = socket.create_server((HOST, 0))
    listener.settimeout(0.1)
    stop = threading.Event()

    def serve(conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            conn.settimeout(10.0)
            f = conn.makefile("rb")
            first = True
            for raw in f:
                line = raw.decode("ascii", "replace").strip()
                out = garbage if first else b""
                first = False
                if line == "*IDN?":
                    out += b"OK Acme,T1,SN-1,1.0\n"
                elif line.startswith("MEAS"):
                    n = int(line.split()[1])
                    points = b"".join(b"PT %d %d.0 1 2 3\n" % (i, i) for i in range(n))
                    out += b"OK %d\n" % n + points + b"END %d\n" % n
                else:
                    out += b"OK\n"
                conn.sendall(out)

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        host, port = listener.getsockname()
        yield f"socket://{host}:{port}"
    finally:
        stop.set()
        thread.join(5)
        listener.close()


MB = 1_000_000
GARBAGE = {
    "one endless line": b"\xaa" * MB,
    "random bytes": random.Random(3).randbytes(MB),
    "text lines": b"hello, this is not the protocol\n" * (MB // 32),
}


@pytest.mark.twin
@pytest.mark.timeout(60)
@pytest.mark.parametrize("kind", list(GARBAGE))
def test_a_megabyte_of_garbage_is_said_for_what_it_is(kind: str) -> None:
    with _talker(GARBAGE[kind]) as url:
        lt = LineTracker("tracker", url, timeout=1.0, reconnects=2, backoff_s=0.01)
        try:
            lt.connect()
            # resynchronised: then it measures like any tracker
            assert lt.identity is not None and lt.measure(3, 100.0).n == 3
        except DeviceError as exc:
            text = _one_line(exc)
            assert "unreachable" not in text, text
            assert "not the tracker line protocol" in text and "first bytes" in text, text
            assert url.removeprefix("socket://") in text, text
        finally:
            lt.close()


@pytest.mark.twin
@pytest.mark.timeout(60)
def test_a_little_garbage_before_the_reply_is_skipped() -> None:
    with _talker(b"booting...\n" + b"\x00\xff" * 100 + b"\n") as url:
        lt = LineTracker("tracker", url, timeout=2.0, reconnects=2, backoff_s=0.01)
        try:
            lt.connect()
            assert lt.identity is not None and lt.identity.maker == "Acme"
            assert lt.garbage == 2 and lt.reconnections == 0
            assert lt.measure(5, 100.0).n == 5
        finally:
            lt.close()


@pytest.mark.timeout(30)
def test_the_measurement_of_a_silent_tracker_is_bounded() -> None:
    """A tracker that says OK to MEAS and then nothing: a timeout, then one reconnection
    per attempt, each bounded, then one error line."""
    t = Answering(lambda req: [f"OK {req.split()[1]}"])
    lt = _tracker(t, reconnects=1)
    with pytest.raises(DeviceError) as info:
        lt.measure(3, 1000.0)
    assert "stalled" in _one_line(info.value)
    assert lt.reconnections == 1


@pytest.mark.timeout(30)
def test_a_link_that_stalls_within_a_line_is_reconnected_not_called_garbage() -> None:
    class HalfLine(Answering):
        def write(self, data: bytes) -> None:
            super().write(data)
            if self.opened == 1 and data.startswith(b"*IDN?"):
                self._out[:] = b"OK Acme,T1"  # and then nothing: the link stalled

    t = HalfLine(lambda req: [f"OK {req.split()[1]}", "END 0"])
    lt = _tracker(t, reconnects=2)
    assert lt.identity is not None and lt.identity.maker == "Acme"
    assert lt.reconnections == 1 and t.opened == 2
