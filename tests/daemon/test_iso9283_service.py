"""An ISO 9283 test run by the service like a calibration (campaign kinds under one
runner): started with ``cellcal campaign start --kind iso9283``, paused, resumed, run to
its end with every pose exactly once, and reported (the stored summary, the report
folder the service writes); its kind shown by the status and the list. The control API
refuses a kind it does not know and a kind's options that are not its own, as one line,
before anything is queued."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call
from cellcal.errors import UserError
from tests.daemon.cells import calibrated_model
from tests.daemon.conftest import small_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]

CYCLES = 2


def stored(d: Any, cid: int) -> int:
    return int(d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {cid}")[0][0])


def test_the_service_starts_pauses_resumes_and_reports_an_iso9283_test(
    folder: Path, daemon: Any
) -> None:
    cell = small_cell(folder)
    model = calibrated_model(folder, cell)
    d = daemon(folder, None, time_scale=0.02, config=cell)
    d.start()

    # Refused in one line, nothing queued: an unknown kind, options of another kind,
    # an ISO test without its calibrated model, a nominal model.
    for body, words in (
        ({"kind": "drift"}, "kind 'drift'"),
        ({"options": {"cycles": 3}}, "a calibration takes no options"),
        ({"kind": "iso9283", "options": {"cycles": 3}}, "needs the calibrated model"),
        ({"kind": "iso9283", "options": "x"}, "options must be a JSON object"),
        (
            {"kind": "iso9283", "options": {"model_toml": model.read_text(), "cycles": 1}},
            "from 2 to 1000",
        ),
        (
            {"kind": "iso9283", "options": {"model_toml": "[x]\n", "model": "m"}},
            "m",
        ),
    ):
        with pytest.raises(UserError) as refused:
            call(d.sock, "POST", "/v1/campaigns", {"when": "now", **body})
        assert words in str(refused.value) and "\n" not in str(refused.value)
    assert d.rows("SELECT COUNT(*) FROM campaigns")[0][0] == 0
    run = cellcal("campaign", "start", "--kind", "iso9283", "--socket", d.sock)
    assert run.returncode == 2 and "--model" in run.stderr and run.stderr.count("\n") == 1

    run = cellcal(
        "campaign", "start", "--kind", "iso9283", "--model", model, "--cycles", CYCLES,
        "--socket", d.sock, "--json",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    answer = json.loads(run.stdout)
    cid, planned = answer["campaign_id"], answer["n_poses"]
    assert planned == 2 * 5 * CYCLES
    # The kind and its options are stored with the campaign (the model's text too).
    (kind,) = d.rows(f"SELECT message FROM events WHERE campaign_id = {cid} AND kind = 'kind'")
    doc = json.loads(kind[0])
    assert doc["kind"] == "iso9283" and doc["options"]["cycles"] == CYCLES
    assert doc["options"]["model"] == str(model.resolve())
    assert doc["options"]["model_toml"] == model.read_text()

    # Deferred pause: the pose under way is finished and stored; nothing moves after.
    d.until(lambda s: s["state"] == "running" and (s["campaign"] or {}).get("stored", 0) >= 2)
    assert call(d.sock, "POST", "/v1/campaigns/current/pause", {})["state"] == "pausing"
    s = d.until(lambda s: s["state"] == "paused")
    n = s["campaign"]["stored"]
    assert 2 <= n < planned and stored(d, cid) == n
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0] == "paused"
    roles = {r for (r,) in d.rows(f"SELECT role FROM poses WHERE campaign_id = {cid}")}
    assert roles == {"iso-before"}
    # Its kind is shown: in the status, by `campaign status` and `campaign list`.
    assert s["campaign"]["kind"] == "iso9283"
    run = cellcal("campaign", "status", "--socket", d.sock)
    assert f"iso9283 campaign {cid} (paused): {n} of {planned} poses stored" in run.stdout
    run = cellcal("campaign", "list", "--socket", d.sock, "--json")
    assert [r["kind"] for r in json.loads(run.stdout)["campaigns"]] == ["iso9283"]

    # Resumed through the CLI, it runs to its end: every pose exactly once, complete.
    run = cellcal("campaign", "resume", str(cid), "--socket", d.sock)
    assert run.returncode == 0, run.stderr
    s = d.until(lambda s: s["state"] == "idle" and "complete" in s["reason"], 120)
    assert d.rows(f"SELECT status FROM campaigns WHERE id = {cid}")[0][0] == "complete"
    idx = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {cid}")]
    assert sorted(idx) == list(range(planned))
    kinds = [k for (k,) in d.rows(f"SELECT kind FROM events WHERE campaign_id = {cid}")]
    assert "iso9283" in kinds and "resumed" in kinds

    # Its report: the stored summary is the ISO 9283 test's, and the service wrote the
    # report folder, titled as the test.
    (summary,) = d.rows(f"SELECT summary FROM reports WHERE campaign_id = {cid}")
    iso = json.loads(summary[0])
    assert iso["cycles"] == CYCLES and iso["calibrated_model"] == str(model.resolve())
    for stage in ("iso-before", "iso-after"):
        points = iso["iso9283"][stage]["points"]
        assert [p["point"] for p in points] == ["P1", "P2", "P3", "P4", "P5"]
        assert all(p["n"] == CYCLES for p in points)
    after = max(p["ap_mm"] for p in iso["iso9283"]["iso-after"]["points"])
    before = min(p["ap_mm"] for p in iso["iso9283"]["iso-before"]["points"])
    assert after < before  # the calibrated model's joints land closer
    report = folder / "reports" / f"campaign-{cid}"
    assert f"report in {report}" in s["reason"]
    page = (report / "index.html").read_text()
    assert f"<title>cellcal ISO 9283 test (campaign {cid})</title>" in page
    assert json.loads((report / "summary.json").read_text())["summary"]["iso9283"] == iso["iso9283"]
    assert d.stop() == 0

    # A service started again shows it, read from the database (no calibration's figures).
    d.start()
    s = d.status()
    assert s["campaign"]["id"] == cid and s["campaign"]["status"] == "complete"
    assert s["campaign"]["kind"] == "iso9283"  # read from the database
    assert s["last_end"] is None or "validation_mm" not in s["last_end"]
    assert d.stop() == 0
