"""A check between calibrations run by the service, as ``cellcal-check.service`` queues
it (``cellcal campaign start --kind check --queue``): without a model in the database it
is refused in one line before anything is queued; after a calibration the service checks
against the cell's current model (the one its own calibration made), records the
verdict and shows the kind."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.daemon.conftest import small_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


def test_the_service_runs_a_queued_check_against_the_current_model(
    folder: Path, daemon: Any
) -> None:
    cell = small_cell(folder)
    d = daemon(folder, None, time_scale=0.0, config=cell)
    d.start()
    refused = cellcal("campaign", "start", "--kind", "check", "--queue", "--socket", d.sock)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1
    assert "no current model in" in refused.stderr and "no calibration is stored" in refused.stderr
    assert d.rows("SELECT COUNT(*) FROM campaigns")[0][0] == 0

    # a calibration run by the service makes the cell's current model
    run = cellcal("campaign", "start", "--socket", d.sock, "--json")
    assert run.returncode == 0, run.stderr
    d.until(lambda s: (s.get("campaign") or {}).get("status") == "complete", 120)
    run = cellcal(
        "campaign", "start", "--kind", "check", "--queue", "--socket", d.sock, "--json"
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    cid = json.loads(run.stdout)["campaign_id"]
    assert json.loads(run.stdout)["n_poses"] == 12
    s = d.until(
        lambda s: (
            (s.get("campaign") or {}).get("id") == cid and s["campaign"].get("status") == "complete"
        ),
        120,
    )
    assert s["campaign"]["id"] == cid and s["campaign"]["kind"] == "check"
    ((verdict, model_id),) = d.rows(
        f"SELECT verdict, model_id FROM checks WHERE campaign_id = {cid}"
    )
    assert (verdict, model_id) == ("ok", 1)
    listed = cellcal("campaign", "list", "--db", d.db, "--json")
    kinds = {c["id"]: c["kind"] for c in json.loads(listed.stdout)["campaigns"]}
    assert kinds == {1: "calibration", cid: "check"}
    d.stop()
