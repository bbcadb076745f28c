"""A slow reader of the service's event stream (``GET /v1/events``, which the status
page follows too) is dropped once it falls ``WATCHER_BACKLOG`` events behind: what
waits for it stays bounded — the service's memory does not grow with it — its
connection is closed at once, publishing never waits for it (the campaign goes on),
and a watcher that keeps up gets every event, in order, meanwhile.

The control API's app served on a Unix socket in the test's folder, in this process;
the slow reader is a plain socket with a small receive buffer that sends its request
and reads nothing more."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Callable
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from cellcal.service.api import WATCHER_BACKLOG, EventHub, make_app
from cellcal.service.control import Control
from cellcal.store.database import Store
from tests.daemon.in_process import service_of

pytestmark = pytest.mark.timeout(120)

#: Events published in all, in batches; each carries this many bytes of payload:
#: together far more than the socket's and aiohttp's buffers take in for the slow one.
EVENTS, BATCH, PAYLOAD = 3000, 50, 2000


async def _until(condition: Callable[[], bool], what: str, timeout: float = 30.0) -> None:
    """Wait (polling the loop) until ``condition()`` holds; fail after ``timeout``."""
    async with asyncio.timeout(timeout):
        while not condition():
            await asyncio.sleep(0.005)
    assert condition(), what


class FastWatcher:
    """Reads the stream as it comes: the ids of the events it got."""

    def __init__(self) -> None:
        self.ids: list[int] = []

    @property
    def last(self) -> int:
        return self.ids[-1] if self.ids else 0

    async def run(self, sock: str) -> None:
        connector = aiohttp.UnixConnector(path=sock)
        async with (
            aiohttp.ClientSession(connector=connector) as session,
            session.get("http://cellcal/v1/events") as resp,
        ):
            assert resp.status == 200
            async for raw in resp.content:
                line = raw.decode()
                if line.startswith("id: "):
                    self.ids.append(int(line[4:]))


def _read_to_the_end(s: socket.socket) -> int:
    """What is left on the slow reader's socket, until the service closed it."""
    s.settimeout(30.0)
    n = 0
    try:
        while chunk := s.recv(65536):
            n += len(chunk)
    except ConnectionResetError:
        pass  # the service closed the dropped reader: what the test waits for
    return n


async def _scenario(folder: Path) -> None:
    sock = str(folder / "control.sock")
    store = Store(str(folder / "events.db"))
    hub = EventHub()
    control = Control(["robot", "tracker"], lambda kind, data: None)
    svc = service_of(store, control, hub, sock)
    runner = web.AppRunner(make_app(svc))
    await runner.setup()
    try:
        await web.UnixSite(runner, sock).start()
        slow = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect(sock)
        slow.sendall(b"GET /v1/events HTTP/1.1\r\nHost: cellcal\r\n\r\n")
        await _until(lambda: len(hub.listeners) == 1, "the slow watcher listens")
        fast = FastWatcher()
        reading = asyncio.create_task(fast.run(sock))
        await _until(lambda: len(hub.listeners) == 2, "the fast watcher listens")
        largest = 0
        payload = "x" * PAYLOAD
        for start in range(0, EVENTS, BATCH):
            for k in range(start, start + BATCH):
                hub.publish("event", {"n": k, "message": payload})  # never waits
            largest = max(largest, *(q.qsize() for q in hub.listeners))
            last = hub.next_id - 1
            await _until(lambda last=last: fast.last >= last, "the fast watcher keeps up")
        # What waited for the slow one never exceeded the bound; it was dropped, once.
        assert largest <= WATCHER_BACKLOG, largest
        assert hub.dropped == 1
        assert len(hub.listeners) == 1  # the fast one
        # Its connection was closed: reading what is left ends (no 30 s send timeout).
        left = await asyncio.to_thread(_read_to_the_end, slow)
        assert left < EVENTS * PAYLOAD
        slow.close()
        # The fast one got every event, in order, none twice.
        published = list(range(1, hub.next_id))
        assert [i for i in fast.ids if i >= 1] == published
        reading.cancel()
        with pytest.raises(asyncio.CancelledError):
            await reading
    finally:
        hub.close()  # as the service stops: each stream ends, so the site closes at once
        await runner.cleanup()
        store.close()


def test_a_slow_reader_is_dropped_and_bounded(tmp_path: Path) -> None:
    asyncio.run(_scenario(tmp_path))
