"""A hostile fake of the cell service for the ``cellcal campaign`` client's tests: it
listens on a Unix socket (a path under the test's tmp_path) and answers every request
the same wrong way — nothing, garbage, an HTML error page, JSON of the wrong kind or
shape, an endless or never-ending answer, a wrong HTTP version, a huge header, a
redirect, text that is not JSON, an event stream of events that are not the service's,
or a valid answer dripped a byte at a time.

It listens once constructed (the socket is bound before the client runs: no wait),
serves from a thread (the client runs ``asyncio.run`` in the test's own thread), each
connection in a thread of its own, and stops when the ``with`` block ends;
``requests`` keeps the head of every request it read (the client's headers)."""

from __future__ import annotations

import contextlib
import socket
import threading
from pathlib import Path


def _http(head: str, body: bytes, content_type: str = "application/json") -> bytes:
    """An HTTP/1.1 answer with its length right."""
    return (
        f"{head}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n"
        "Connection: close\r\n\r\n"
    ).encode() + body


#: What each behaviour answers (the others are written as they go by ``HostileService._answer``).
FIXED = {
    "garbage": b"\x00\xff\xfe garbage \x1b[31m not HTTP at all\r\n\r\n\x00\x01",
    "html-500": _http(
        "HTTP/1.1 500 Internal Server Error",
        b"<html><body><h1>500 Internal Error</h1></body></html>",
        "text/html",
    ),
    "not-an-object": _http("HTTP/1.1 200 OK", b"[1, 2, 3]"),
    "wrong-shape": _http("HTTP/1.1 200 OK", b'{"state": 5, "devices": "no", "campaigns": 7}'),
    "wrong-version": _http("HTTP/7.3 200 OK", b"{}"),
    "huge-header": _http("HTTP/1.1 200 OK\r\nX-Filler: " + "a" * 200_000, b"{}"),
    "redirect": _http("HTTP/1.1 302 Found\r\nLocation: http://cellcal/v1/status", b""),
    "not-json": _http("HTTP/1.1 200 OK", b"this is not JSON at all"),
    # an event stream whose events are not the service's: a list, a NaN, an id of text
    "bad-events": _http(
        "HTTP/1.1 200 OK",
        b'event: status\ndata: [1, 2]\n\nevent: pose\ndata: {"stored": NaN}\n\nid: x\n\n',
        "text/event-stream",
    ),
}
#: A valid-looking answer the slow drip sends a byte at a time.
DRIPPED = _http("HTTP/1.1 200 OK", b"{}")
BEHAVIOURS = (
    "close",
    *FIXED,
    "endless-body",
    "never-answers",
    "slow-drip",
)


class HostileService:
    """``with HostileService(path, behaviour):`` serves until the block ends."""

    def __init__(self, path: Path, behaviour: str, drip_s: float = 0.3) -> None:
        assert behaviour in BEHAVIOURS, behaviour
        assert len(str(path)) < 100, path  # Unix socket paths are limited
        self.path, self.behaviour, self.drip_s = path, behaviour, drip_s
        self.requests: list[bytes] = []
        self.stopped = threading.Event()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(path))
        self.sock.listen(16)
        self.sock.settimeout(0.1)
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> HostileService:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stopped.set()
        self.thread.join(5)
        self.sock.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    def _serve(self) -> None:
        while not self.stopped.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._connection, args=(conn,), daemon=True).start()

    def _read_head(self, conn: socket.socket) -> bytes:
        head = b""
        conn.settimeout(5)
        with contextlib.suppress(OSError):
            while b"\r\n\r\n" not in head and len(head) < 65536:
                chunk = conn.recv(4096)
                if not chunk:
                    break
                head += chunk
        self.requests.append(head)
        return head

    def _connection(self, conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            self._read_head(conn)
            self._answer(conn)
            # let the client read what was sent before the connection goes
            conn.shutdown(socket.SHUT_WR)
            conn.settimeout(2)
            with contextlib.suppress(OSError):
                while conn.recv(4096):
                    pass

    def _answer(self, conn: socket.socket) -> None:
        b = self.behaviour
        if b == "close":
            return
        if b in FIXED:
            conn.sendall(FIXED[b])
        elif b == "endless-body":
            conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n\r\n[")
            chunk = b'"endless", ' * 6000
            while not self.stopped.is_set():
                conn.sendall(chunk)
        elif b == "never-answers":
            self.stopped.wait()
        elif b == "slow-drip":
            for byte in DRIPPED:
                if self.stopped.wait(self.drip_s):
                    return
                conn.sendall(bytes([byte]))
