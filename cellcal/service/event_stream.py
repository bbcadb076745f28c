"""The control API's event stream (``GET /v1/events``, also served by the status page):
server-sent events out of one hub.

The hub (:class:`EventHub`, loop thread only) numbers every event, keeps the last
``EVENT_BUFFER`` for watchers that reconnect with ``Last-Event-ID``, and hands each to
every listener's bounded queue. A stream sends what its watcher missed, a status, then
what the hub publishes; a keep-alive comment when quiet. What waits for each watcher is
bounded: one that falls ``WATCHER_BACKLOG`` events behind, or takes nothing in for
``SEND_TIMEOUT_S``, is dropped (its connection closed), so a slow watcher neither grows
the service nor holds up the campaign, which never waits for a watcher."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections import deque
from collections.abc import Callable
from typing import Any

from aiohttp import web

log = logging.getLogger("cellcal.service")

#: Events kept for ``Last-Event-ID``.
EVENT_BUFFER = 2000
#: Seconds between keep-alive comments on a quiet event stream: a watcher that hears
#: nothing for much longer knows the service is gone or hung.
KEEPALIVE_S = 15.0
#: Seconds a watcher may take to take in what is sent to it; a slower one is dropped.
SEND_TIMEOUT_S = 30.0
#: Events that may wait for one watcher; one further behind is dropped. Half the replay
#: buffer: a dropped watcher that reconnects with ``Last-Event-ID`` finds what it missed.
WATCHER_BACKLOG = EVENT_BUFFER // 2

#: What an event stream's queue holds: an event (id, kind, data), or its end: ``None``
#: (the service stops) or :data:`BEHIND` (the watcher fell behind and is dropped).
Item = tuple[int, str, str] | None | str
BEHIND = "behind"


class EventHub:
    """The event stream's buffer and its listeners (loop thread only). Each listener's
    queue holds at most :data:`WATCHER_BACKLOG` events: publishing never waits, and a
    listener that falls further behind is dropped at once — its queue emptied and ended,
    its ``drop`` called (which closes its connection).

    ``status_view``: what a ``status`` event carries beyond the control's snapshot (the
    service's API sets it: the campaign's kind, read from the database)."""

    def __init__(self) -> None:
        self.next_id = 1
        self.buffer: deque[tuple[int, str, str]] = deque(maxlen=EVENT_BUFFER)
        self.listeners: dict[asyncio.Queue[Item], Callable[[], None]] = {}
        self.dropped = 0  # listeners dropped for falling behind
        self.status_view: Callable[[dict[str, Any]], dict[str, Any]] = lambda snap: snap

    def listen(self, drop: Callable[[], None] = lambda: None) -> asyncio.Queue[Item]:
        """A new listener's queue, bounded; ``drop``: called if it falls behind."""
        q: asyncio.Queue[Item] = asyncio.Queue(maxsize=WATCHER_BACKLOG)
        self.listeners[q] = drop
        return q

    def publish(self, kind: str, data: dict[str, Any]) -> None:
        if kind == "status":
            data = self.status_view(data)
        item = (self.next_id, kind, json.dumps(data, separators=(",", ":")))
        self.next_id += 1
        self.buffer.append(item)
        for q in list(self.listeners):
            try:
                q.put_nowait(item)
            except asyncio.QueueFull:
                drop = self.listeners.pop(q)
                self.dropped += 1
                _end(q, BEHIND)
                drop()

    def since(self, last_id: int) -> list[tuple[int, str, str]]:
        return [e for e in self.buffer if e[0] > last_id]

    def close(self) -> None:
        """The service stops: each stream ends after what waits for it (a full one now)."""
        for q in self.listeners:
            try:
                q.put_nowait(None)
            except asyncio.QueueFull:
                _end(q, None)


def _end(q: asyncio.Queue[Item], mark: Item) -> None:
    """End a listener's stream: what waits in its queue is dropped, ``mark`` follows."""
    while not q.empty():
        q.get_nowait()
    q.put_nowait(mark)


async def event_stream(
    request: web.Request, hub: EventHub, snapshot: Callable[[], dict[str, Any]]
) -> web.StreamResponse:
    """Server-sent events: ``status``, ``pose``, ``event``, ``campaign-end``; a client
    that reconnects with ``Last-Event-ID`` gets what it missed (while buffered), a new
    one starts from now with ``snapshot()``."""
    resp = web.StreamResponse(
        headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"}
    )
    await resp.prepare(request)
    header = request.headers.get("Last-Event-ID")
    try:
        last = int(header) if header else None
    except ValueError:
        last = None
    # A new watcher starts from now (with a snapshot); one that reconnects gets what
    # it missed, as far as the buffer reaches.
    backlog = hub.since(last) if last is not None else []

    def behind() -> None:  # dropped for falling behind: closed at once, a send with it
        log.info("an event stream's reader fell %d events behind: dropped", WATCHER_BACKLOG)
        if request.transport is not None:
            request.transport.abort()

    q = hub.listen(behind)
    # A watcher that goes away (or is dropped) ends its stream; nothing else is wrong.
    try:
        with contextlib.suppress(ConnectionResetError):
            await _stream_events(hub, snapshot, resp, q, backlog)
    except TimeoutError:  # a watcher that does not read: dropped, its descriptor freed
        log.info("an event stream's reader took nothing for %.0f s: dropped", SEND_TIMEOUT_S)
        if request.transport is not None:
            request.transport.abort()
    return resp


async def _stream_events(
    hub: EventHub,
    snapshot: Callable[[], dict[str, Any]],
    resp: web.StreamResponse,
    q: asyncio.Queue[Item],
    backlog: list[tuple[int, str, str]],
) -> None:
    """The backlog, a status, then what the hub publishes, until the stream's end."""
    try:
        for item in backlog:
            await _send(resp, item)
        if not backlog or backlog[-1][1] != "status":
            snap = json.dumps(snapshot())
            await _send(resp, (hub.next_id - 1, "status", snap))
        while True:
            try:
                async with asyncio.timeout(KEEPALIVE_S):
                    pending = await q.get()
            except TimeoutError:
                await _write(resp, b": keep-alive\n\n")  # a comment: EventSource skips it
                continue
            if pending is None or isinstance(pending, str):
                return
            await _send(resp, pending)
    finally:
        hub.listeners.pop(q, None)


async def _send(resp: web.StreamResponse, item: tuple[int, str, str]) -> None:
    i, kind, data = item
    await _write(resp, f"id: {i}\nevent: {kind}\ndata: {data}\n\n".encode())


async def _write(resp: web.StreamResponse, data: bytes) -> None:
    """Out to one watcher, which must take it within ``SEND_TIMEOUT_S`` (TimeoutError)."""
    async with asyncio.timeout(SEND_TIMEOUT_S):
        await resp.write(data)
