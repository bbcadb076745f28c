"""Hostile control requests against the service (a subprocess in mock mode): each is
answered in the API's error shape ``{"error": {"code", "message"}}`` with a 4xx status,
one line of message — never a 500, never acted on — and the service goes on serving.

Among them the five that got HTTP 500 (issue 29): a ``config_name`` that is not a
string, JSON nested a hundred thousand deep, a number of 5 000 digits, a lone surrogate,
a campaign id beyond SQLite's integers; and those that were accepted and should not
have been: a seed above 2³²−1 (it trapped the engine in a loop), a JSON boolean as a
seed, ``mock: "yes"``, a body that is not ``application/json``, an unknown field, a
request that reached the service after its deadline."""

from __future__ import annotations

import json
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cellcal.service.api_requests import SEED_MAX, start_request
from tests.daemon.conftest import Daemon, serving, small_cell

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(180)]

CODES = {"invalid-state", "invalid-params", "not-found", "devices-not-ready", "forbidden"}
JSON = {"Content-Type": "application/json"}
START = "/v1/campaigns"


def request(
    sock: str,
    method: str,
    path: str,
    body: bytes = b"",
    headers: dict[str, str] | None = None,
) -> tuple[int, bytes]:
    """One raw HTTP/1.1 request on the Unix socket: the status and the body."""
    head = {"Host": "cellcal", "Connection": "close", "Content-Length": str(len(body))}
    head.update(headers or {})
    lines = "".join(f"{k}: {v}\r\n" for k, v in head.items())
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(20)
        s.connect(sock)
        s.sendall(f"{method} {path} HTTP/1.1\r\n{lines}\r\n".encode() + body)
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    top, _, rest = answer.partition(b"\r\n\r\n")
    return int(top.split(b" ", 2)[1]), rest


@pytest.fixture(scope="module")
def service() -> Iterator[Daemon]:
    folder = Path(tempfile.mkdtemp(prefix="cc-svc-", dir="/tmp"))
    with serving(Daemon(folder, None, 0.02, config=small_cell(folder))) as d:
        yield d


def _deep(n: int) -> bytes:
    return b'{"when": ' + b"[" * n + b"]" * n + b"}"


CASES: dict[str, tuple[str, str, bytes, dict[str, str]]] = {
    # the five 500s
    "config_name an object": ("POST", START, b'{"config_name": {}, "when": "queue"}', JSON),
    "nested 100 000 deep": ("POST", START, _deep(100_000), JSON),
    "a 5000-digit number": ("POST", START, b'{"seed": ' + b"9" * 5000 + b"}", JSON),
    "a lone surrogate": ("POST", START, b'{"config_name": "\\ud800", "when": "queue"}', JSON),
    "an id beyond SQLite": ("POST", "/v1/campaigns/99999999999999999999999/abort", b"", {}),
    "GET an id beyond SQLite": ("GET", "/v1/campaigns/99999999999999999999999", b"", {}),
    # accepted, and should not have been
    "seed 2**32": ("POST", START, b'{"seed": 4294967296, "when": "queue"}', JSON),
    "seed 2**64": ("POST", START, b'{"seed": 18446744073709551616, "when": "queue"}', JSON),
    "seed true": ("POST", START, b'{"seed": true, "when": "queue"}', JSON),
    "mock a string": ("POST", START, b'{"mock": "yes", "when": "queue"}', JSON),
    "not application/json": ("POST", START, b'{"when": "queue"}', {"Content-Type": "text/plain"}),
    "an unknown field": ("POST", START, b'{"when": "queue", "priority": 1}', JSON),
    # refused before, in the error shape or not
    "malformed JSON": ("POST", START, b"{", JSON),
    "JSON not an object": ("POST", START, b"[]", JSON),
    "a JSON number": ("POST", START, b"5", JSON),
    "not UTF-8": ("POST", START, b'{"when": "\xff"}', JSON),
    "1e400": ("POST", START, b'{"seed": 1e400}', JSON),
    "NaN": ("POST", START, b'{"seed": NaN}', JSON),
    "seed -1": ("POST", START, b'{"seed": -1, "when": "queue"}', JSON),
    "seed 1.5": ("POST", START, b'{"seed": 1.5, "when": "queue"}', JSON),
    "when a list": ("POST", START, b'{"when": []}', JSON),
    "mode an object": ("POST", "/v1/campaigns/current/pause", b'{"mode": {}}', JSON),
    "config_toml a number": ("POST", START, b'{"config_toml": 5, "when": "queue"}', JSON),
    "a body of 2 MiB": ("POST", START, b'{"x": "' + b"a" * (2 * 1024 * 1024) + b'"}', JSON),
    "an id not a number": ("POST", "/v1/campaigns/%FF/abort", b"", {}),
    "a limit of 5000 digits": ("GET", "/v1/campaigns?limit=" + "9" * 5000, b"", {}),
    "PUT": ("PUT", START, b"{}", JSON),
    "no such route": ("GET", "/v2/" + "x" * 3000, b"", {}),
    # a start whose client gave up long ago (it timed out while the service was flooded)
    "past its deadline": (
        "POST",
        START,
        b'{"when": "queue"}',
        {**JSON, "Cellcal-Deadline": f"{time.time() - 44:.3f}"},
    ),
    "a deadline not a time": (
        "POST",
        START,
        b'{"when": "queue"}',
        {**JSON, "Cellcal-Deadline": "tomorrow"},
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_hostile_request_is_refused_in_the_api_shape(service: Daemon, case: str) -> None:
    method, path, body, headers = CASES[case]
    before = service.rows("SELECT COUNT(*) FROM campaigns")
    status, raw = request(service.sock, method, path, body, headers)
    assert 400 <= status < 500, (status, raw[:300])
    answer: Any = json.loads(raw)
    assert set(answer) == {"error"}, answer
    error = answer["error"]
    assert error["code"] in CODES, error
    message = error["message"]
    assert isinstance(message, str) and message and "\n" not in message, error
    assert len(message) < 300, message  # a quoted piece of the request is cut short
    # nothing was queued or started, and the service goes on serving
    assert service.rows("SELECT COUNT(*) FROM campaigns") == before
    assert service.status()["state"] in ("idle", "running")


def test_the_service_logged_no_traceback(service: Daemon) -> None:
    for case in ("config_name an object", "nested 100 000 deep"):
        request(service.sock, *CASES[case])
    assert "Traceback" not in service.tail()


@pytest.mark.parametrize(
    ("seed", "ok"),
    [(0, True), (SEED_MAX, True), (SEED_MAX + 1, False), (-1, False), (True, False), (1.0, False)],
)
def test_a_seed_is_a_whole_number_from_0_to_2_32_minus_1(seed: Any, ok: bool) -> None:
    from cellcal.service.api_requests import RequestError

    if ok:
        assert start_request({"seed": seed}).seed == seed
    else:
        with pytest.raises(RequestError, match="seed"):
            start_request({"seed": seed})
