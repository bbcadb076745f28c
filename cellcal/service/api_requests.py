"""The control API's requests, read with bounds and checked before anything acts on them.

A body is JSON (``Content-Type: application/json``, else 415), at most ``MAX_BODY``
bytes (else 413), read within ``BODY_TIMEOUT_S`` (else 408), UTF-8 without lone
surrogates, numbers finite and of at most ``MAX_DIGITS`` digits, a JSON object with
only the fields the call knows, each of its type (a JSON boolean is not a number).
A campaign id is a whole number SQLite can hold. A request that names its deadline
(``Cellcal-Deadline``, Unix time in seconds, sent by ``cellcal campaign``) and reaches
the service after it is dropped (408): its client gave up on it, so nothing is done.
Each refusal is a :class:`RequestError`: the API's error code, one line, its HTTP status.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from dataclasses import dataclass
from typing import Any

from aiohttp import web

from cellcal.service.control import ControlError

#: The largest body a request may have (bytes): a configuration's text fits many times.
MAX_BODY = 1024 * 1024
#: Seconds a request's body may take to arrive.
BODY_TIMEOUT_S = 10.0
#: The most digits a JSON number may have (a seed has 10).
MAX_DIGITS = 20
#: The header that says until when the client waits for its request (Unix time, s).
DEADLINE_HEADER = "Cellcal-Deadline"
#: Seeds: what numpy's generators accept and SQLite stores (as the configuration's).
SEED_MAX = 2**32 - 1
#: Campaign ids: SQLite's integers.
ID_MAX = 2**63 - 1
#: The longest piece of a request quoted back in an error line.
QUOTE = 40


class RequestError(ControlError):
    """A request refused before anything acts on it: code, one line, HTTP status."""

    def __init__(self, code: str, message: str, status: int = 400) -> None:
        super().__init__(code, message)
        self.status = status


def invalid(message: str, status: int = 400) -> RequestError:
    return RequestError("invalid-params", message, status)


def quote(value: object) -> str:
    """A value of the request, quoted in one short line."""
    text = repr(value)
    return text if len(text) <= QUOTE else text[: QUOTE - 1] + "…"


@dataclass(frozen=True)
class StartRequest:
    """``POST /v1/campaigns``."""

    config_toml: str | None = None
    config_name: str | None = None
    mock: bool | None = None
    seed: int | None = None
    when: str = "now"
    #: the campaign's kind (``kinds.all_kinds()``; absent: a calibration) and its options,
    #: a JSON object the kind checks (an ISO 9283 test: cycles, model, model_toml)
    kind: str = "calibration"
    options: dict[str, Any] | None = None


@dataclass(frozen=True)
class PauseRequest:
    """``POST /v1/campaigns/{id}/pause``."""

    mode: str = "deferred"


def check_deadline(request: web.Request) -> None:
    """Refuse a request its client no longer waits for (see the module docstring)."""
    raw = request.headers.get(DEADLINE_HEADER)
    if raw is None:
        return
    try:
        deadline = float(raw)
    except ValueError:
        deadline = math.nan
    if not math.isfinite(deadline):
        raise invalid(f"{DEADLINE_HEADER} {quote(raw)}: give a Unix time in seconds")
    late = time.time() - deadline
    if late > 0:
        raise invalid(
            f"the request arrived {late:.1f} s after its deadline ({DEADLINE_HEADER}): its "
            "client gave up on it, so nothing was done",
            408,
        )


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def _finite(text: str) -> float:
    if len(text.lstrip("-").split(".")[0].split("e")[0].split("E")[0]) > MAX_DIGITS:
        raise ValueError(f"the number {quote(text)} has more than {MAX_DIGITS} digits")
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"the number {quote(text)} is not finite")
    return value


def _whole(text: str) -> int:
    if len(text.lstrip("-")) > MAX_DIGITS:
        raise ValueError(f"the number {quote(text)} has more than {MAX_DIGITS} digits")
    return int(text)


def parse_json(raw: bytes) -> Any:
    """A body's JSON (see the module docstring); :class:`RequestError` if it is not."""
    try:
        text = raw.decode("utf-8")
        value = json.loads(
            text, parse_constant=_refuse_constant, parse_float=_finite, parse_int=_whole
        )
        # a lone surrogate (\ud800) decodes, but no file, log or database takes it
        json.dumps(value, ensure_ascii=False).encode("utf-8")
    except UnicodeError:
        raise invalid("the body is not UTF-8 text (or holds a lone surrogate)") from None
    except json.JSONDecodeError as exc:
        raise invalid(f"the body is not JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise invalid("the body's JSON is nested too deeply") from None
    except ValueError as exc:  # a number refused by _finite, _whole, _refuse_constant
        raise invalid(f"the body's JSON: {exc}") from None
    return value


async def read_body(request: web.Request, fields: tuple[str, ...]) -> dict[str, Any]:
    """A request's body as a JSON object with only ``fields`` (none sent: empty)."""
    if not request.body_exists:
        return {}
    if request.content_type != "application/json":
        raise invalid(f"the body is {quote(request.content_type)}; send application/json", 415)
    if request.content_length is not None and request.content_length > MAX_BODY:
        raise invalid(f"the body is larger than {MAX_BODY // 1024} KiB", 413)
    try:
        async with asyncio.timeout(BODY_TIMEOUT_S):
            raw = await request.read()
    except TimeoutError:
        raise invalid(f"the body did not arrive within {BODY_TIMEOUT_S:.0f} s", 408) from None
    except web.HTTPRequestEntityTooLarge:
        raise invalid(f"the body is larger than {MAX_BODY // 1024} KiB", 413) from None
    body = parse_json(raw) if raw else {}
    if not isinstance(body, dict):
        raise invalid(f"the body must be a JSON object, not a JSON {_kind(body)}")
    unknown = sorted(set(body) - set(fields))
    if unknown:
        known = ", ".join(fields) if fields else "none"
        raise invalid(f"unknown field {quote(unknown[0])} (this call takes: {known})")
    return body


def _kind(value: Any) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean"}.get(
        type(value), "number" if isinstance(value, (int, float)) else "null"
    )


def _text(body: dict[str, Any], key: str, *, line: bool = False) -> str | None:
    value = body.get(key)
    if value is None:
        return None
    if not isinstance(value, str):
        raise invalid(f"{key} must be a string, not a JSON {_kind(value)}")
    if line and any(not c.isprintable() for c in value):
        raise invalid(f"{key} {quote(value)} holds control characters")
    return value


def _choice(body: dict[str, Any], key: str, choices: tuple[str, ...]) -> str:
    value = body.get(key, choices[0])
    if value not in choices or not isinstance(value, str):
        raise invalid(f"{key} {quote(value)}: {' or '.join(choices)}")
    return value


def start_request(body: dict[str, Any]) -> StartRequest:
    mock = body.get("mock")
    if mock is not None and not isinstance(mock, bool):
        raise invalid(f"mock must be true or false, not a JSON {_kind(mock)}")
    seed = body.get("seed")
    if seed is not None and (
        isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX
    ):
        raise invalid(f"seed {quote(seed)} must be a whole number from 0 to {SEED_MAX}")
    return StartRequest(
        config_toml=_text(body, "config_toml"),
        config_name=_text(body, "config_name", line=True),
        mock=mock,
        seed=seed,
        when=_choice(body, "when", ("now", "queue")),
        kind=_text(body, "kind", line=True) or "calibration",
        options=_object(body, "options"),
    )


def _object(body: dict[str, Any], key: str) -> dict[str, Any] | None:
    value = body.get(key)
    if value is not None and not isinstance(value, dict):
        raise invalid(f"{key} must be a JSON object, not a JSON {_kind(value)}")
    return value


START_FIELDS = tuple(StartRequest.__dataclass_fields__)
PAUSE_FIELDS = tuple(PauseRequest.__dataclass_fields__)


def pause_request(body: dict[str, Any]) -> PauseRequest:
    return PauseRequest(mode=_choice(body, "mode", ("deferred", "immediate")))


def campaign_number(raw: str) -> int:
    """A campaign id of the path: a whole number from 1 to SQLite's largest."""
    if not (raw.isascii() and raw.isdigit()):
        raise invalid(f"campaign id {quote(raw)} is not a number")
    if len(raw) > 19 or not 1 <= int(raw) <= ID_MAX:
        raise RequestError("not-found", f"no campaign {quote(raw)}: ids run from 1 to {ID_MAX}")
    return int(raw)


def limit_of(raw: str) -> int:
    """``?limit=N`` of a list: a whole number, at most 100 000."""
    if not (raw.isascii() and raw.isdigit()) or len(raw) > 9:
        raise invalid(f"limit {quote(raw)} must be a whole number from 0 to 100000")
    return min(int(raw), 100_000)
