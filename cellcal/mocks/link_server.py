"""A reusable link server for the twins, protocol-agnostic: ``TcpLinkServer`` listens on
a (loopback) host:port, ``PtyLinkServer`` serves a pseudo-terminal.

A server runs ``handler(link)`` for each connection in a thread of its own (a TCP
connection accepted; a client's opening the pty's slave path, so a close and a reopen make
a new connection). Over its ``Link`` the handler has ``wait(timeout)`` (something to read,
or the peer closed), ``read()`` (the bytes there are: b"" when nothing is there yet, None
when the peer closed), ``write(data)`` (all of it, or ``LinkClosedError`` when the link is
gone or the server stops) and ``stop``, the server's stop event: serve until it is set.

The handler ends its connection by returning or by letting ``LinkClosedError`` out. It
raises ``DropLinkError`` to drop the connection (fault injection): a TCP connection is
shut down (FIN), a pty stops answering (its input is read and dropped) until the client
closes and reopens it. Any other exception is logged and ends the connection the same way,
so does a client that reads none of its replies for ``WRITE_STALL_S`` (with a log line).

``stop()`` sets the stop event (several servers may share one), joins the threads, which
close the sockets and the pty; ``connections`` counts the connections served.

Size (about 500 lines): the TCP and pty servers share the ``Link`` and the serving
thread's life cycle, whose stop and stall handling must stay in one place; split the pty
server into a module of its own if either grows.
"""

from __future__ import annotations

import abc
import contextlib
import ctypes
import logging
import math
import os
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from typing import Self

_log = logging.getLogger("cellcal.mocks.link_server")

POLL_S = 0.05  # the longest a serving loop waits before it looks at the stop flag
JOIN_S = 2.0  # how long ``stop`` waits for the threads by default
#: A client that takes none of a reply for this long (one sending requests faster than it
#: reads) is closed: else it holds its connection's thread, and all it holds, for ever.
WRITE_STALL_S = 10.0
_READ = 65536

LinkHandler = Callable[["Link"], None]


class LinkClosedError(Exception):
    """The link is gone (peer closed, error) or the server is stopping."""


class DropLinkError(Exception):
    """Raised by a handler: drop the connection now (fault injection)."""


class SlowReaderError(LinkClosedError):
    """The client has taken none of a reply for :data:`WRITE_STALL_S`: it is closed."""


# ---------------------------------------------------------------------------- links


class Link(abc.ABC):
    """Bytes to and from one client over a non-blocking descriptor; a subclass says how
    a descriptor of its kind receives and sends."""

    def __init__(self, fd: int, stop: threading.Event) -> None:
        self.fd = fd
        self.stop = stop
        self.poller = select.poll()
        self.poller.register(fd, select.POLLIN)

    def wait(self, timeout: float) -> bool:
        """Whether there is something to read (or the peer closed) within ``timeout`` s."""
        return bool(self.poller.poll(max(0, math.ceil(timeout * 1000))))

    def read(self) -> bytes | None:
        """The bytes there are; b"" when nothing is there yet, None when the peer closed."""
        try:
            return self._recv() or None
        except BlockingIOError:
            return b""
        except OSError:  # the peer is gone (a pty: EIO, no client has the slave open)
            return None

    @abc.abstractmethod
    def _recv(self) -> bytes:
        """One non-blocking read (b"" at end of stream; BlockingIOError when empty)."""

    @abc.abstractmethod
    def _send(self, data: memoryview) -> int:
        """One non-blocking write; the number of bytes sent."""

    def check_open(self) -> None:  # noqa: B027 - a hook with a default, not abstract
        """Raise ``LinkClosedError`` when the peer is known to be gone. A socket tells
        only when written to, so by default nothing is known here; a pty can tell
        (``PtyLink``)."""

    def write(self, data: bytes) -> None:
        """Send all of ``data``; ``LinkClosedError`` when the link is gone or stopping,
        ``SlowReaderError`` when the client takes none of it for :data:`WRITE_STALL_S`."""
        view = memoryview(data)
        out = select.poll()
        out.register(self.fd, select.POLLOUT)
        moved = time.monotonic()
        while view:
            if self.stop.is_set():
                raise LinkClosedError
            self.check_open()
            try:
                sent = self._send(view)
            except BlockingIOError:
                sent = 0
            except OSError as exc:
                raise LinkClosedError from exc
            view = view[sent:]
            if not view:
                return
            now = time.monotonic()
            if sent:
                moved = now
            elif now - moved > WRITE_STALL_S:
                raise SlowReaderError(
                    f"{len(view)} bytes of replies not taken for {WRITE_STALL_S:g} s"
                )
            out.poll(int(POLL_S * 1000))


class SocketLink(Link):
    """A connected non-blocking socket."""

    def __init__(self, sock: socket.socket, stop: threading.Event) -> None:
        super().__init__(sock.fileno(), stop)
        self.sock = sock

    def _recv(self) -> bytes:
        return self.sock.recv(_READ)

    def _send(self, data: memoryview) -> int:
        return self.sock.send(data)


class PtyLink(Link):
    """The master side of a pty, and who has its slave open.

    With inotify (Linux) the server keeps the slave open itself, so the master never
    hangs up, and follows the clients' opens and closes of the slave path: a close and
    an immediate reopen are two events, never missed. Elsewhere a client closing shows as
    a hang-up on the master (best effort: a reopen faster than the server looks is seen
    as the same connection).
    """

    def __init__(self, master: int, slave: int, path: str, stop: threading.Event) -> None:
        super().__init__(master, stop)
        self.path = path
        self.watch = _inotify_watch(path)  # after the slave was opened: ours is no event
        self.keeper: int | None = slave
        if self.watch is None:
            os.close(slave)
            self.keeper = None
        else:
            self.poller.register(self.watch, select.POLLIN)
        self.clients = 0
        self.opens = 0
        self.pending: deque[int] = deque()
        self.early = b""  # read while waiting for the client: its first bytes, unread yet

    def close(self) -> None:
        for fd in (self.watch, self.keeper, self.fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)

    def connected(self) -> bool:
        """Whether the client of the session has the slave open. With inotify, the events
        after the last client's close stay queued: they belong to the next connection."""
        if self.watch is None:
            return not _pty_hung_up(self.fd)
        return self._follow(to_hangup=True)

    def _follow(self, *, to_hangup: bool) -> bool:
        """Count the opens and closes reported so far; whether a client has it open."""
        assert self.watch is not None
        self.pending.extend(_inotify_events(self.watch))
        while self.pending:
            mask = self.pending.popleft()
            if mask & _IN_OPEN:
                self.clients += 1
                self.opens += 1
            elif mask & _IN_CLOSE and self.clients > 0:
                self.clients -= 1
                if self.clients == 0 and to_hangup:
                    return False
        return self.clients > 0

    def wait_open(self, carry: bytes = b"") -> bytes | None:
        """Wait until a client has the slave open. Returns the bytes already read that may
        be its first request (``carry`` included), or None when the server stops."""
        if self.watch is None:
            while not self.stop.is_set():
                if not _pty_hung_up(self.fd):
                    return carry
                self.stop.wait(0.01)
            return None
        return self._wait_for(lambda: self._follow(to_hangup=False), carry)

    def mute_until_reopened(self) -> bytes | None:
        """Read and drop everything until the client closes the slave and opens it again
        (without inotify: until it closes). Returns as ``wait_open`` does."""
        if self.watch is None:
            while not self.stop.is_set():
                if self.wait(POLL_S) and self.read() is None:
                    return b""
            return None
        opens = self.opens

        def reopened() -> bool:
            self._follow(to_hangup=False)
            return self.opens > opens

        return self._wait_for(reopened)

    def _wait_for(self, condition: Callable[[], bool], carry: bytes = b"") -> bytes | None:
        """Drop input until ``condition`` holds. An open is reported before the opener can
        write, so bytes read before the condition turned true may be a new client's
        request: those are handed back, not dropped."""
        while not self.stop.is_set():
            if condition():
                return carry
            carry = b""
            if self.wait(POLL_S):
                with contextlib.suppress(OSError):
                    carry = os.read(self.fd, _READ)
        return None

    def flush_stale(self) -> None:
        """Drop what the server wrote and no client read: a pty keeps unread output for
        the next opener, who must not see replies meant for the last one."""
        fd = self.keeper
        if fd is None:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            except OSError:
                return
        try:
            # A pty whose other end is gone cannot be flushed: nothing stale is left.
            with contextlib.suppress(termios.error):
                termios.tcflush(fd, termios.TCIFLUSH)
        finally:
            if fd != self.keeper:
                os.close(fd)

    def wait(self, timeout: float) -> bool:
        return bool(self.early) or super().wait(timeout)

    def read(self) -> bytes | None:
        if self.early:
            data, self.early = self.early, b""
            return data
        if not self.connected():
            return None
        return super().read()

    def _recv(self) -> bytes:
        return os.read(self.fd, _READ)

    def check_open(self) -> None:
        if not self.connected():
            raise LinkClosedError

    def _send(self, data: memoryview) -> int:
        return os.write(self.fd, data)


def _pty_hung_up(master: int) -> bool:
    poller = select.poll()
    poller.register(master, select.POLLIN)
    return any(ev & select.POLLHUP for _, ev in poller.poll(0))


_IN_OPEN = 0x20
_IN_CLOSE = 0x08 | 0x10  # IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
_INOTIFY_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)


def _inotify_watch(path: str) -> int | None:
    """An inotify descriptor reporting opens and closes of ``path``, or None where there is
    no inotify."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fd = int(libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC))
    except (OSError, AttributeError):
        return None
    if fd < 0:
        return None
    if libc.inotify_add_watch(fd, os.fsencode(path), _IN_OPEN | _IN_CLOSE) < 0:
        os.close(fd)
        return None
    return fd


def _inotify_events(fd: int) -> list[int]:
    masks: list[int] = []
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:  # BlockingIOError included: nothing more to read
            return masks
        offset = 0
        while offset + _INOTIFY_EVENT.size <= len(data):
            _, mask, _, name_len = _INOTIFY_EVENT.unpack_from(data, offset)
            masks.append(mask)
            offset += _INOTIFY_EVENT.size + name_len


# ---------------------------------------------------------------------------- servers


class _LinkServer:
    """What the TCP and the pty server share: threads, stop, the count of connections."""

    def __init__(
        self,
        handler: LinkHandler,
        *,
        name: str = "link",
        stop: threading.Event | None = None,
        log: logging.Logger | None = None,
    ) -> None:
        self.handler = handler
        self.name = name
        self.stop_event = stop if stop is not None else threading.Event()
        self.log = log if log is not None else _log
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._connections = 0
        self._started = False

    @property
    def connections(self) -> int:
        """Connections served so far: TCP connections accepted, pty opens seen."""
        with self._lock:
            return self._connections

    @property
    def threads(self) -> list[threading.Thread]:
        """The serving threads still running."""
        with self._lock:
            self._threads = [t for t in self._threads if t.is_alive()]
            return list(self._threads)

    def stop(self, timeout: float = JOIN_S) -> None:
        """Stop serving: set the stop event, join the threads (they close the listening
        socket, the connections and the pty) for at most ``timeout`` seconds."""
        self.stop_event.set()
        deadline = time.monotonic() + timeout
        while True:
            threads = self.threads
            if not threads:
                return
            for thread in threads:
                thread.join(max(0.0, deadline - time.monotonic()))
            if time.monotonic() >= deadline:
                alive = [t.name for t in self.threads]
                if alive:
                    self.log.warning("%s: threads still running after stop: %s", self.name, alive)
                return

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _begin(self, what: str) -> None:
        if self._started:
            raise RuntimeError(f"{self.name}: {what} already started")
        if self.stop_event.is_set():
            raise RuntimeError(f"{self.name}: stopped")

    def _spawn(self, target: Callable[..., None], *args: object, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        with self._lock:  # started first: ``threads`` drops a thread not alive
            thread.start()
            self._threads.append(thread)

    def _run(self, link: Link, drop: str) -> bool:
        """Run the handler over one connection; False when it dropped the connection
        (``DropLinkError``, logged with ``drop``) or failed."""
        try:
            self.handler(link)
        except SlowReaderError as exc:
            self.log.warning(
                "%s: the client does not read its replies (%s); closing the connection",
                self.name,
                exc,
            )
            return False
        except LinkClosedError:
            return True  # the peer went away or the server is stopping: a normal end
        except DropLinkError:
            self.log.info("%s: %s (fault injection)", self.name, drop)
            return False
        except Exception:
            self.log.exception("%s: connection failed", self.name)
            return False
        return True

    def _count_connection(self) -> int:
        with self._lock:
            self._connections += 1
            return self._connections


class TcpLinkServer(_LinkServer):
    """Listens on a (loopback) host:port and runs ``handler(SocketLink)`` for each
    accepted connection, in a thread of its own."""

    def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Listen on (host, port) (port 0: any free one) and serve in the background;
        returns the bound address once listening."""
        self._begin("TCP")
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((host, port))
            listener.listen(8)
            listener.settimeout(POLL_S)
        except OSError:
            listener.close()
            raise
        self._started = True
        bound = listener.getsockname()
        self._spawn(self._accept, listener, name=f"{self.name}-tcp-{bound[1]}")
        return str(bound[0]), int(bound[1])

    def _accept(self, listener: socket.socket) -> None:
        try:
            while not self.stop_event.is_set():
                try:
                    conn, _ = listener.accept()
                except TimeoutError:
                    continue
                except OSError as exc:
                    self.log.warning("%s: accept failed (%s)", self.name, exc)
                    self.stop_event.wait(POLL_S)
                    continue
                n = self._count_connection()
                self._spawn(self._serve, conn, name=f"{self.name}-conn-{n}")
        finally:
            listener.close()

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            conn.setblocking(False)
            with contextlib.suppress(OSError):
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if not self._run(SocketLink(conn, self.stop_event), "dropping the connection"):
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)


class PtyLinkServer(_LinkServer):
    """Creates a pseudo-terminal and runs ``handler(PtyLink)`` each time a client has
    opened its slave side, one connection after the other, in one thread."""

    def start(self) -> str:
        """Open a pseudo-terminal, serve its master side in the background and return the
        slave's path (open it with pyserial, e.g. ``serial.Serial(path)``)."""
        self._begin("pty")
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no line discipline: bytes pass untouched
            path = os.ttyname(slave)
            os.set_blocking(master, False)
            link = PtyLink(master, slave, path, self.stop_event)
        except OSError:
            os.close(master)
            os.close(slave)
            raise
        self._started = True
        self._spawn(self._serve, link, name=f"{self.name}-pty")
        return path

    def _serve(self, link: PtyLink) -> None:
        try:
            carry = link.wait_open()
            while carry is not None:
                self._count_connection()
                link.early = carry  # handed to the handler as its first read
                ended = self._run(link, "the pty stops answering until reopened")
                link.early = b""
                carry = b"" if ended else link.mute_until_reopened()
                link.flush_stale()
                if carry is not None:
                    carry = link.wait_open(carry)
        finally:
            link.close()
