"""Who may use the control socket, tested with real credentials: the service runs as
root with its socket 0660 in a 0750 folder (group root); a client forked into uid 65534
is refused by the kernel, the same uid with the socket's group among its groups is
accepted, and — should the files be opened to everyone by mistake — the service's own
SO_PEERCRED check still answers ``forbidden`` and changes nothing."""

from __future__ import annotations

import json
import os
import socket
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pytestmark = [
    pytest.mark.twin,
    pytest.mark.timeout(120),
    pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as another uid"),
]

NOBODY = 65534


def as_user(path: str, request: bytes, uid: int, groups: list[int]) -> str:
    """One HTTP request on the Unix socket from a child process with these credentials:
    the status line and body, or ``ERR <errno name>``."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: drop to the credentials, ask, report through the pipe
        out = b""
        try:
            os.close(r)
            os.setgroups(groups)
            os.setgid(groups[0])
            os.setuid(uid)
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(10)
                s.connect(path)
                s.sendall(request)
                while chunk := s.recv(65536):
                    out += chunk
            head, _, body = out.partition(b"\r\n\r\n")
            out = head.split(b"\r\n")[0] + b"\n" + body
        except OSError as exc:
            out = f"ERR {os.strerror(exc.errno or 0)}".encode()
        finally:
            os.write(w, out)
            os._exit(0)
    os.close(w)
    chunks = []
    while chunk := os.read(r, 65536):
        chunks.append(chunk)
    os.close(r)
    os.waitpid(pid, 0)
    return b"".join(chunks).decode()


def http(method: str, path: str, body: dict[str, Any] | None = None) -> bytes:
    data = json.dumps(body).encode() if body is not None else b""
    head = f"{method} {path} HTTP/1.1\r\nHost: cellcal\r\nConnection: close\r\n"
    head += f"Content-Type: application/json\r\nContent-Length: {len(data)}\r\n\r\n"
    return head.encode() + data


def test_another_uid_is_refused_and_a_group_member_accepted(
    folder: Path, daemon: Callable[..., Any]
) -> None:
    os.chmod(folder, 0o755)  # as /run is: the socket's own folder is what guards it
    d = daemon(folder, None, 0.02)
    d.start()
    sock = Path(d.sock)
    assert stat.S_IMODE(sock.stat().st_mode) == 0o660
    assert stat.S_IMODE(sock.parent.stat().st_mode) == 0o750
    group = sock.parent.stat().st_gid
    assert sock.stat().st_gid == group

    refused = as_user(d.sock, http("GET", "/v1/status"), NOBODY, [NOBODY])
    assert refused == "ERR Permission denied"

    status = as_user(d.sock, http("GET", "/v1/status"), NOBODY, [NOBODY, group])
    assert status.startswith("HTTP/1.1 200"), status
    assert json.loads(status.split("\n", 1)[1])["state"] == "idle"
    # A member may act: the refusal is the state's, not the caller's.
    pause = as_user(d.sock, http("POST", "/v1/campaigns/current/pause"), NOBODY, [NOBODY, group])
    assert pause.startswith("HTTP/1.1 409"), pause
    assert json.loads(pause.split("\n", 1)[1])["error"]["code"] == "invalid-state"
    queued = as_user(d.sock, http("POST", "/v1/campaigns", {"when": "queue"}), NOBODY, [0])
    assert queued.startswith("HTTP/1.1 202"), queued
    cid = json.loads(queued.split("\n", 1)[1])["campaign_id"]
    who = d.rows(f"SELECT message FROM events WHERE campaign_id = {cid} AND kind = 'operator'")
    assert who and f"uid {NOBODY} (nobody)" in who[0][0]

    # The files opened to everyone by mistake: the service still refuses a stranger.
    os.chmod(sock.parent, 0o755)
    os.chmod(sock, 0o666)
    forbidden = as_user(d.sock, http("POST", "/v1/campaigns/current/abort"), NOBODY, [NOBODY])
    assert forbidden.startswith("HTTP/1.1 403"), forbidden
    error = json.loads(forbidden.split("\n", 1)[1])["error"]
    assert error["code"] == "forbidden" and f"uid {NOBODY}" in error["message"]
    status_after = d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0]
    assert status_after in ("queued", "running", "analysing", "complete")
    assert d.stop() == 0
