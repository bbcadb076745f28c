"""The CLI's side of the control API: one request to the service over its Unix socket
(aiohttp's client), or the event stream read line by line. Every failure is one line
naming the socket: the service's own error message, or what is wrong with the socket,
the connection or the answer (not HTTP, not JSON, not an object, too large, too slow, a
redirect) and what to type.

Whatever answers on the socket is read with bounds: an answer of at most
``MAX_ANSWER`` bytes within ``REQUEST_TIMEOUT_S``; on the event stream, the answer's
head within ``REQUEST_TIMEOUT_S``, events of at most ``MAX_EVENT`` bytes, and never
more than ``EVENT_SILENCE_S`` without a line (the service sends a keep-alive comment
every 15 s). Each request carries its deadline (``Cellcal-Deadline``, Unix time): the
service drops a request that reaches it after the client gave up on it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

import aiohttp
from aiohttp.http_exceptions import HttpProcessingError

from cellcal.errors import UserError

DEFAULT_SOCKET = "/run/cellcal/control.sock"
#: Seconds a control request may take (connecting, sending, the whole answer).
REQUEST_TIMEOUT_S = 30.0
#: Seconds the event stream may stay silent: three of the service's keep-alives.
EVENT_SILENCE_S = 50.0
#: The largest answer read (bytes): a list of thousands of campaigns fits.
MAX_ANSWER = 16 * 1024 * 1024
#: The largest event of the stream (bytes).
MAX_EVENT = 1024 * 1024
#: The request's header that says until when its client waits for it (Unix time, s).
DEADLINE_HEADER = "Cellcal-Deadline"
#: The longest message of the service's quoted in an error line.
MAX_MESSAGE = 300


def socket_path(option: str | None) -> str:
    """``--socket``, else ``$CELLCAL_SOCKET``, else the service's path under systemd."""
    return option or os.environ.get("CELLCAL_SOCKET") or DEFAULT_SOCKET


def one_line(text: object, limit: int = MAX_MESSAGE) -> str:
    """Text from the other end, fit for one line of a terminal: control characters
    (escape sequences, line breaks) become spaces, and it is cut at ``limit``."""
    clean = "".join(c if c.isprintable() else " " for c in str(text))
    clean = " ".join(clean.split())
    return clean if len(clean) <= limit else clean[: limit - 1] + "…"


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


def _what_broke(exc: BaseException, timeout_s: float) -> str:
    """What a connection that broke, or an answer that is not HTTP, came to."""
    if isinstance(exc, TimeoutError):
        return f"no complete answer within {timeout_s:.0f} s"
    if isinstance(exc, aiohttp.ServerDisconnectedError):
        return "the connection was closed without a complete answer"
    if isinstance(exc, (aiohttp.ClientResponseError, HttpProcessingError)):
        detail = getattr(exc, "message", "") or exc
        return f"the answer is not HTTP/1.1 as cellcal speaks it ({one_line(detail, 120)})"
    if isinstance(exc, aiohttp.ClientPayloadError):
        return f"the answer broke off ({one_line(exc, 120)})"
    return f"{type(exc).__name__} ({one_line(exc, 120)})"


def _broken(sock: str, exc: BaseException) -> UserError:
    if isinstance(exc, aiohttp.ClientConnectorError):
        return _unreachable(sock, exc)
    what = _what_broke(exc, REQUEST_TIMEOUT_S)
    return UserError(f"{sock}: {what}; is a cellcal service listening there?")


def _session(sock: str, timeout: aiohttp.ClientTimeout) -> aiohttp.ClientSession:
    return aiohttp.ClientSession(connector=aiohttp.UnixConnector(path=sock), timeout=timeout)


async def _read(resp: aiohttp.ClientResponse, sock: str) -> bytes:
    """The answer's body, refused past ``MAX_ANSWER`` bytes."""
    chunks: list[bytes] = []
    size = 0
    async for chunk in resp.content.iter_chunked(64 * 1024):
        size += len(chunk)
        if size > MAX_ANSWER:
            raise UserError(
                f"{sock}: the answer is larger than {MAX_ANSWER // (1024 * 1024)} MiB; "
                "is a cellcal service listening there?"
            )
        chunks.append(chunk)
    return b"".join(chunks)


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _json(raw: bytes) -> Any:
    """JSON as the service writes it: UTF-8, finite numbers."""
    return json.loads(raw.decode("utf-8"), parse_constant=_refuse_constant)


def _message_of(data: Any) -> str | None:
    """The service's one line in an error answer (``{"error": {"code", "message"}}``)."""
    err = data.get("error") if isinstance(data, dict) else None
    message = err.get("message") if isinstance(err, dict) else None
    return one_line(message) if isinstance(message, str) and message else None


async def _refusal(resp: aiohttp.ClientResponse) -> str | None:
    """The service's one line in an error answer of the event stream, if it sent one."""
    try:
        async with asyncio.timeout(REQUEST_TIMEOUT_S):
            return _message_of(_json(await resp.content.read(64 * 1024)))
    except (OSError, aiohttp.ClientError, HttpProcessingError, ValueError):
        return None


async def _request(sock: str, method: str, path: str, body: dict[str, Any] | None) -> Any:
    deadline = time.time() + REQUEST_TIMEOUT_S
    headers = {DEADLINE_HEADER: f"{deadline:.3f}"}
    timeout = aiohttp.ClientTimeout(total=REQUEST_TIMEOUT_S)
    try:
        async with (
            _session(sock, timeout) as session,
            session.request(
                method, f"http://cellcal{path}", json=body, headers=headers, allow_redirects=False
            ) as resp,
        ):
            raw = await _read(resp, sock)
            status, location = resp.status, resp.headers.get("Location", "")
    except UserError:
        raise
    except (OSError, aiohttp.ClientError, HttpProcessingError, ValueError) as exc:
        # OSError: TimeoutError, a refused or reset connection; ValueError: a header the
        # client's parser refuses
        raise _broken(sock, exc) from None
    if 300 <= status < 400:
        raise UserError(
            f"{sock}: the answer is a redirect ({status} to {one_line(location, 80)!r}); "
            "a cellcal service never redirects: is it one?"
        )
    try:
        data = _json(raw)
    except ValueError:  # JSONDecodeError, UnicodeDecodeError, NaN
        raise UserError(
            f"{sock}: the answer ({status}) is not JSON; is a cellcal service listening there?"
        ) from None
    if status >= 400:
        message = _message_of(data)
        if message:
            raise UserError(message)
        raise UserError(f"{sock}: the service answered {status} without an error message")
    if not isinstance(data, dict):
        raise UserError(
            f"{sock}: the answer is a JSON {type(data).__name__}, not an object; "
            "is a cellcal service listening there?"
        )
    return data


def call(sock: str, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
    """One request; the answer's JSON object."""
    return asyncio.run(_request(sock, method, path, body))


@contextlib.contextmanager
def answer_of(sock: str, what: str) -> Iterator[None]:
    """Reading what the service sent (an answer, an event): a missing key or a value of
    the wrong kind ends in one line naming the socket, not a traceback."""
    try:
        yield
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        detail = f"no {one_line(exc.args[0], 60)!r}" if isinstance(exc, KeyError) else exc
        raise UserError(
            f"{sock}: the service's {what} is not what this cellcal expects "
            f"({one_line(detail, 120)}); is it a cellcal service of this version?"
        ) from None


def _field(line: str) -> tuple[str, str]:
    name, _, value = line.partition(":")
    return name, value.removeprefix(" ")


async def _open_events(
    session: aiohttp.ClientSession, sock: str, last_id: int
) -> aiohttp.ClientResponse:
    """The event stream's answer, its head read within ``REQUEST_TIMEOUT_S``."""
    headers = {"Last-Event-ID": str(last_id)} if last_id else {}
    try:
        async with asyncio.timeout(REQUEST_TIMEOUT_S):
            url = "http://cellcal/v1/events"
            resp = await session.get(url, headers=headers, allow_redirects=False)
    except (OSError, aiohttp.ClientError, HttpProcessingError, ValueError) as exc:
        raise _broken(sock, exc) from None
    kind = resp.headers.get("Content-Type", "").partition(";")[0].strip()
    if resp.status >= 400 and kind == "application/json":
        message = await _refusal(resp)  # the service's own line (forbidden, …)
        if message:
            raise UserError(message)
    if resp.status != 200 or kind != "text/event-stream":
        resp.release()
        raise UserError(
            f"{sock}: the event stream answered {resp.status} "
            f"({one_line(kind or 'no content type', 60)}), not an event stream; "
            "is a cellcal service listening there?"
        )
    return resp


def _not_events(sock: str, what: str) -> UserError:
    return UserError(f"{sock}: the event stream is not what cellcal expects ({what})")


def _event_data(sock: str, data: str) -> Any:
    try:
        return _json(data.encode("utf-8"))
    except ValueError as exc:  # not JSON, or a NaN
        raise _not_events(sock, f"an event's data is not JSON: {one_line(exc, 80)}") from None


async def _events(sock: str, last_id: int) -> AsyncIterator[tuple[int, str, Any]]:
    session = _session(sock, aiohttp.ClientTimeout(total=None, sock_connect=REQUEST_TIMEOUT_S))
    try:
        resp = await _open_events(session, sock, last_id)
        event_id, kind, data = 0, "message", ""
        while True:
            async with asyncio.timeout(EVENT_SILENCE_S):
                raw = await resp.content.readline(max_line_length=MAX_EVENT)
            if not raw:
                return  # the service closed the stream
            try:
                line = raw.decode("utf-8").rstrip("\r\n")
            except UnicodeDecodeError:
                raise _not_events(sock, "a line is not UTF-8") from None
            name, value = _field(line)
            if not line:
                if data:
                    yield event_id, kind, _event_data(sock, data)
                event_id, kind, data = 0, "message", ""
            elif name == "id":
                if not value.isdigit() or len(value) > 18:
                    raise _not_events(sock, f"id {one_line(value, 40)!r} is not a number")
                event_id = int(value)
            elif name == "event":
                kind = value.strip()
            elif name == "data":
                data += value
                if len(data) > MAX_EVENT:
                    raise _not_events(sock, "an event is larger than 1 MiB")
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
        except aiohttp.ClientConnectorError as exc:
            raise _unreachable(sock, exc) from None
        except TimeoutError:
            raise UserError(
                f"{sock}: the event stream said nothing for {EVENT_SILENCE_S:.0f} s "
                "(a cellcal service sends a keep-alive every 15 s); is it hung? "
                "systemctl status cellcal"
            ) from None
        except (OSError, aiohttp.ClientError, HttpProcessingError) as exc:
            what = _what_broke(exc, EVENT_SILENCE_S)
            raise UserError(f"{sock}: the event stream broke: {what}") from None
        return False

    return asyncio.run(run())
