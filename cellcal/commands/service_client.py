"""The CLI's side of the control API: one request to the service over its Unix socket
(aiohttp's client), or the event stream read line by line. Every failure is one line:
the service's own error message, or what is wrong with the socket and what to type."""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import AsyncIterator, Callable
from typing import Any

import aiohttp

from cellcal.errors import UserError

DEFAULT_SOCKET = "/run/cellcal/control.sock"
#: Seconds a control request may take.
REQUEST_TIMEOUT_S = 30.0


def socket_path(option: str | None) -> str:
    """``--socket``, else ``$CELLCAL_SOCKET``, else the service's path under systemd."""
    return option or os.environ.get("CELLCAL_SOCKET") or DEFAULT_SOCKET


def _unreachable(sock: str, exc: aiohttp.ClientConnectorError | OSError) -> UserError:
    os_error = getattr(exc, "os_error", exc)
    if isinstance(os_error, PermissionError):
        return UserError(
            f"{sock}: permission denied; operators join group cellcal "
            "(sudo usermod -aG cellcal $USER, then log in again)"
        )
    return UserError(
        f"no cellcal service at {sock} (is it running? systemctl status cellcal; "
        "or give --socket / CELLCAL_SOCKET)"
    )


def _session(sock: str) -> aiohttp.ClientSession:
    return aiohttp.ClientSession(
        connector=aiohttp.UnixConnector(path=sock),
        timeout=aiohttp.ClientTimeout(total=REQUEST_TIMEOUT_S),
    )


async def _request(sock: str, method: str, path: str, body: dict[str, Any] | None) -> Any:
    try:
        async with (
            _session(sock) as session,
            session.request(method, f"http://cellcal{path}", json=body) as resp,
        ):
            try:
                data = await resp.json(content_type=None)
            except (json.JSONDecodeError, aiohttp.ContentTypeError):
                raise UserError(
                    f"{sock}: the service answered {resp.status} without JSON"
                ) from None
    except aiohttp.ClientConnectorError as exc:
        raise _unreachable(sock, exc) from None
    except (TimeoutError, aiohttp.ClientError) as exc:
        raise UserError(f"{sock}: {type(exc).__name__} talking to the service ({exc})") from None
    if resp.status >= 400:
        err = data.get("error", {}) if isinstance(data, dict) else {}
        raise UserError(str(err.get("message") or f"the service answered {resp.status}"))
    return data


def call(sock: str, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
    """One request; the answer's JSON."""
    return asyncio.run(_request(sock, method, path, body))


async def _events(sock: str, last_id: int) -> AsyncIterator[tuple[int, str, Any]]:
    headers = {"Last-Event-ID": str(last_id)} if last_id else {}
    session = aiohttp.ClientSession(
        connector=aiohttp.UnixConnector(path=sock),
        timeout=aiohttp.ClientTimeout(total=None, sock_read=None),
    )
    try:
        async with session.get("http://cellcal/v1/events", headers=headers) as resp:
            if resp.status != 200:
                raise UserError(f"{sock}: the event stream answered {resp.status}")
            event_id, kind, data = 0, "message", ""
            async for raw in resp.content:
                line = raw.decode("utf-8").rstrip("\r\n")
                if not line:
                    if data:
                        yield event_id, kind, json.loads(data)
                    event_id, kind, data = 0, "message", ""
                elif line.startswith("id:"):
                    event_id = int(line[3:].strip())
                elif line.startswith("event:"):
                    kind = line[6:].strip()
                elif line.startswith("data:"):
                    data += line[5:].strip()
    except aiohttp.ClientConnectorError as exc:
        raise _unreachable(sock, exc) from None
    finally:
        await session.close()


def follow(sock: str, handle: Callable[[int, str, Any], bool]) -> bool:
    """Read the event stream, handing each event to ``handle`` until it returns True
    (then True) or the service closes the stream (then False)."""

    async def run() -> bool:
        try:
            async for event_id, kind, data in _events(sock, 0):
                if handle(event_id, kind, data):
                    return True
        except aiohttp.ClientPayloadError:
            return False  # the service closed the stream mid-event (it stopped)
        except aiohttp.ClientError as exc:
            raise UserError(f"{sock}: the event stream broke ({exc})") from None
        return False

    return asyncio.run(run())
