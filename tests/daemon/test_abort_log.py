"""An abort is logged by the service: one line naming the campaign, whether it was
running (the robot stopped at once) or paused, interrupted or queued. A campaign that
stops, or is aborted, has no ETA in the status any more."""

from __future__ import annotations

import logging

import pytest

from cellcal.service.control import Control


def _control() -> Control:
    return Control(["robot"], lambda kind, data: None)


def _lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "cellcal.control"]


def test_aborting_the_running_campaign_is_one_log_line(caplog: pytest.LogCaptureFixture) -> None:
    c = _control()
    c.state, c.campaign = "running", {"id": 3, "stored": 1, "planned": 10}
    with caplog.at_level(logging.INFO, logger="cellcal.control"):
        assert c.abort(None, lambda cid: "running") == ("aborting", 3)
    (line,) = _lines(caplog)
    assert "campaign 3" in line and "abort" in line and "\n" not in line


def test_aborting_a_paused_campaign_is_one_log_line(caplog: pytest.LogCaptureFixture) -> None:
    c = _control()
    c.state, c.blocking = "paused", 4
    c.campaign = {"id": 4, "stored": 5, "planned": 10, "status": "paused"}
    with caplog.at_level(logging.INFO, logger="cellcal.control"):
        assert c.abort(4, lambda cid: "paused") == ("aborted", 4)
    (line,) = _lines(caplog)
    assert line == "campaign 4 aborted (it was paused)"
    assert c.state == "idle"


@pytest.mark.parametrize("status", ["paused", "interrupted", "complete"])
def test_a_stopped_campaign_has_no_eta(status: str) -> None:
    c = _control()
    c.state = "running"
    c.campaign = {"id": 5, "stored": 6, "planned": 128, "status": "running", "eta_s": 108.7}
    c.finished(5, status, "operator")
    snap = c.snapshot()["campaign"]
    assert snap["status"] == status and "eta_s" not in snap
    if status == "paused":
        c.abort(5, lambda cid: "paused")
        assert "eta_s" not in c.snapshot()["campaign"]
