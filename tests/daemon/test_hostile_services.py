"""The ``cellcal campaign`` client against hostile services: whatever answers on the
socket — nothing, garbage, an HTML error page, JSON of the wrong kind or shape, an
endless or never-ending answer, a wrong HTTP version, a huge header, a redirect, text
that is not JSON, a slow drip — every command ends in one line ``cellcal: error: …``
naming the socket, exit 2: never a traceback, never a hang."""

from __future__ import annotations

from pathlib import Path

import pytest

import cellcal.commands.service_client as service_client
from cellcal.cli import main
from tests.daemon.hostile_service import BEHAVIOURS, HostileService

pytestmark = pytest.mark.timeout(30)

COMMANDS = {
    "status": ["campaign", "status"],
    "start": ["campaign", "start", "--mock"],
    "watch": ["campaign", "watch"],
    "list": ["campaign", "list"],
    "pause": ["campaign", "pause"],
    "resume": ["campaign", "resume", "3"],
    "abort": ["campaign", "abort"],
}


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    with pytest.raises(SystemExit) as ended:
        main(args)
    code = ended.value.code
    return (code if isinstance(code, int) else 1), capsys.readouterr().err


@pytest.fixture(autouse=True)
def short_timeouts(monkeypatch: pytest.MonkeyPatch) -> None:
    """The client's timeouts, shortened so that a service that never answers costs the
    test under a second, not thirty: still longer than the slow drip's pause between
    bytes (0.3 s), so the drip is ended by the request's deadline, not by a read."""
    monkeypatch.setattr(service_client, "REQUEST_TIMEOUT_S", 0.8)
    monkeypatch.setattr(service_client, "EVENT_SILENCE_S", 0.8, raising=False)


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("behaviour", BEHAVIOURS)
def test_every_command_ends_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], behaviour: str, command: str
) -> None:
    sock = tmp_path / "s"
    with HostileService(sock, behaviour):
        code, err = _run([*COMMANDS[command], "--socket", str(sock)], capsys)
    lines = err.splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith("cellcal: error: "), err
    assert str(sock) in lines[0], err
    assert "\x1b" not in err and "\x00" not in err, err  # the service's bytes, not echoed raw


def test_a_request_carries_its_deadline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A control request says until when it is wanted: the service drops one that
    arrives after its client gave up (a start that timed out must not run later)."""
    sock = tmp_path / "s"
    with HostileService(sock, "html-500") as fake:
        code, _ = _run(["campaign", "start", "--mock", "--socket", str(sock)], capsys)
    assert code == 2
    head = fake.requests[0].decode("latin-1").lower()
    assert "\r\ncellcal-deadline: " in head, head
