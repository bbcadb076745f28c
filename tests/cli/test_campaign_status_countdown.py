"""``cellcal campaign status`` gives a countdown only while the campaign goes on: not
while it is pausing (it stops after the pose under way), paused or being aborted; and it
names the campaign's kind (none from a service of an earlier cellcal)."""

from __future__ import annotations

from typing import Any

import pytest
from click.testing import CliRunner

import cellcal.commands.campaign as campaign_cli


def _status(monkeypatch: pytest.MonkeyPatch, state: str, status: str, **more: Any) -> str:
    snap: dict[str, Any] = {
        "state": state,
        "reason": f"campaign 2: {state}",
        "campaign": {
            "id": 2,
            "status": status,
            "stored": 40,
            "planned": 128,
            "phase": "dwell",
            "eta_s": 1234.0,
            **more,
        },
        "devices": {"robot": {"state": "ready"}},
        "queue": [],
        "paused_campaign": 2 if state == "paused" else None,
    }
    monkeypatch.setattr(campaign_cli, "call", lambda sock, method, path, body=None: snap)
    result = CliRunner().invoke(campaign_cli.campaign, ["status", "--socket", "/run/none.sock"])
    assert result.exit_code == 0, result.output
    return result.output


def test_a_running_campaign_has_a_countdown(monkeypatch: pytest.MonkeyPatch) -> None:
    assert "about 1234 s to go" in _status(monkeypatch, "running", "running")


@pytest.mark.parametrize(
    ("state", "status"), [("pausing", "running"), ("paused", "paused"), ("aborting", "running")]
)
def test_no_countdown_unless_it_goes_on(
    monkeypatch: pytest.MonkeyPatch, state: str, status: str
) -> None:
    out = _status(monkeypatch, state, status)
    assert "to go," not in out and "s to go" not in out
    assert "40 of 128 poses stored" in out


def test_the_status_names_the_campaigns_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    out = _status(monkeypatch, "paused", "paused", kind="iso9283")
    assert "iso9283 campaign 2 (paused): 40 of 128 poses stored" in out.splitlines()[1]
    out = _status(monkeypatch, "paused", "paused", kind="\x1b[2J")  # one line, no escape
    assert "\x1b" not in out and out.splitlines()[1].startswith("[2J campaign 2 (paused)")
    out = _status(monkeypatch, "paused", "paused")  # an earlier service: no kind
    assert out.splitlines()[1].startswith("campaign 2 (paused): 40 of 128")
