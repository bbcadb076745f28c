"""Bounds on the service's connections, so that no client — a flood of idle
connections to the status page, a slow one, a stuck one — takes the service's file
descriptors or its control socket from it.

- The open files limit (RLIMIT_NOFILE) is raised from its soft value to the hard one at
  start, and a budget is drawn from it: ``RESERVE_FDS`` descriptors stay for the engine
  (database, devices, reports), ``BACKLOG`` per site for connections being refused, a
  share goes to the control socket (at most
  ``CONTROL_MAX`` connections), the rest to the status page (at most ``PAGE_MAX``).
- Each listening socket hands its connections through a :class:`Gate`: past its share,
  a new connection is answered ``503`` at once and closed (said in the log at most once
  every ``LOG_EVERY_S``), so the page's flood never reaches the descriptors the control
  socket and the engine need.
- A connection idle for ``IDLE_TIMEOUT_S`` — before its first request is complete, or
  between two — is closed (aiohttp's ``keepalive_timeout``).
- asyncio logs every failed accept when the descriptors run out anyway (up to the
  backlog's length each time the socket is ready: thousands of lines a second); the
  loop's exception handler (:class:`AcceptErrors`) folds them into one line every
  ``LOG_EVERY_S``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import resource
import time
from dataclasses import dataclass
from typing import Any

from aiohttp import web

log = logging.getLogger("cellcal.service")

#: Seconds a connection may stay idle (no request under way) before it is closed.
IDLE_TIMEOUT_S = 10.0
#: Connections at most on the control socket, and on the status page.
CONTROL_MAX = 64
PAGE_MAX = 512
#: Descriptors kept free of connections: the engine's database, devices and reports.
RESERVE_FDS = 64
#: Connections a listening socket queues, and accepts at once when it is ready: a
#: refused one holds its descriptor until the next turn of the loop, so each site may
#: hold this many beyond its share for a moment.
BACKLOG = 32
#: A refusal, or a failed accept, is logged at most once in this many seconds.
LOG_EVERY_S = 10.0
#: asyncio's message for a failed accept (EMFILE, ENFILE, ENOBUFS, ENOMEM).
ACCEPT_FAILED = "socket.accept() out of system resource"


@dataclass(frozen=True)
class Budget:
    """The descriptors the service may use, and the connections each site may hold."""

    limit: int  # RLIMIT_NOFILE's soft limit, once raised
    in_use: int  # open at start
    control: int
    page: int


def _open_descriptors() -> int:
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 32  # a guess where /proc is not mounted


def descriptor_budget() -> Budget:
    """Raise the open files limit to its hard value and share it out (module docstring)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and (soft == resource.RLIM_INFINITY or soft < hard):
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError) as exc:
            log.warning("the open files limit stays %d (not raised to %d: %s)", soft, hard, exc)
    limit = soft if soft != resource.RLIM_INFINITY else 1 << 20
    in_use = _open_descriptors()
    free = max(0, limit - in_use - RESERVE_FDS - 2 * BACKLOG)
    control = max(4, min(CONTROL_MAX, free // 4))
    page = max(4, min(PAGE_MAX, free - control))
    if control + page > free:
        log.warning(
            "the open files limit (%d) is low: %d connections at most on the control socket "
            "and %d on the status page may leave the engine short (LimitNOFILE=)",
            limit,
            control,
            page,
        )
    return Budget(limit, in_use, control, page)


class _Counted(asyncio.Protocol):
    """aiohttp's protocol for one connection, counted by its gate until it is lost."""

    def __init__(self, inner: asyncio.Protocol, gate: Gate) -> None:
        self.inner, self.gate = inner, gate

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received()

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self.gate.open -= 1
        self.inner.connection_lost(exc)


class _Refused(asyncio.Protocol):
    """A connection past the gate's limit: answered at once, then closed."""

    def __init__(self, answer: bytes) -> None:
        self.answer = answer

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.WriteTransport)
        transport.write(self.answer)
        transport.close()


def refusal(status: str, content_type: str, body: bytes) -> bytes:
    """An HTTP/1.1 answer that closes the connection."""
    head = (
        f"HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n"
        f"Retry-After: {IDLE_TIMEOUT_S:.0f}\r\nConnection: close\r\n\r\n"
    )
    return head.encode() + body


class Gate:
    """The protocol factory in front of aiohttp's server: at most ``limit`` connections
    open; past it, each new one gets ``answer`` and is closed."""

    def __init__(self, server: web.Server, limit: int, name: str, answer: bytes) -> None:
        self.server, self.limit, self.name, self.answer = server, limit, name, answer
        self.open = 0
        self.refused = 0  # since the last line in the log
        self.said = -LOG_EVERY_S

    def __call__(self) -> asyncio.Protocol:
        if self.open >= self.limit:
            self.refused += 1
            now = time.monotonic()
            if now - self.said >= LOG_EVERY_S:
                log.warning(
                    "%s: %d connections open, the most it takes; %d refused since the last "
                    "such line (idle ones are closed after %.0f s)",
                    self.name,
                    self.open,
                    self.refused,
                    IDLE_TIMEOUT_S,
                )
                self.said, self.refused = now, 0
            return _Refused(self.answer)
        self.open += 1
        return _Counted(self.server(), self)


class GatedSite(web.BaseSite):
    """A site whose listening socket — TCP (``host``, ``port``) or Unix (``path``) —
    hands its connections through a :class:`Gate`."""

    def __init__(
        self,
        runner: web.AppRunner,
        *,
        limit: int,
        name: str,
        answer: bytes,
        host: str | None = None,
        port: int = 0,
        path: str | None = None,
    ) -> None:
        super().__init__(runner, backlog=BACKLOG)
        self.limit, self.label, self.answer = limit, name, answer
        self.host, self.port, self.path = host, port, path
        self.gate: Gate | None = None

    @property
    def name(self) -> str:
        return f"http://unix:{self.path}:" if self.path else f"http://{self.host}:{self.port}"

    async def start(self) -> None:
        await super().start()
        server = self._runner.server
        assert server is not None
        self.gate = Gate(server, self.limit, self.label, self.answer)
        loop = asyncio.get_running_loop()
        if self.path is not None:
            self._server = await loop.create_unix_server(
                self.gate, self.path, backlog=self._backlog
            )
        else:
            self._server = await loop.create_server(
                self.gate, self.host, self.port, backlog=self._backlog
            )


class AcceptErrors:
    """The loop's exception handler: failed accepts folded into one line every
    ``LOG_EVERY_S`` (module docstring); anything else goes to asyncio's own handler."""

    def __init__(self) -> None:
        self.count = 0
        self.said = -LOG_EVERY_S

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if context.get("message") != ACCEPT_FAILED:
            loop.default_exception_handler(context)
            return
        self.count += 1
        now = time.monotonic()
        if now - self.said < LOG_EVERY_S:
            return
        sock = context.get("socket")
        where = sock.getsockname() if sock is not None else "a listening socket"
        log.error(
            "cannot accept connections on %s: %s (%d times since the last such line); "
            "the open files limit is %d",
            where or "the control socket",
            context.get("exception"),
            self.count,
            resource.getrlimit(resource.RLIMIT_NOFILE)[0],
        )
        self.said, self.count = now, 0
