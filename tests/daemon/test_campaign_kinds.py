"""Campaign kinds under one runner (``cellcal/campaign/runner.py``): an ISO 9283 test
started by the runner, stopped after a few poses and resumed from its database like a
calibration (``cellcal run --resume``), with its kind and options read back from the
campaign; a campaign without a stored kind is a calibration; unknown kinds and options
of another kind are refused in one line."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from cellcal.campaign.iso9283_kind import IsoOutcome
from cellcal.campaign.kinds import all_kinds, stored_kind
from cellcal.campaign.records import PoseStored, Record
from cellcal.campaign.runner import resume_campaign, start_campaign
from cellcal.config import load_config
from cellcal.errors import InputError
from cellcal.store.database import Store
from tests.daemon.cells import CALIBRATION_DB, calibrated_model
from tests.daemon.conftest import small_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(240)]


def test_an_iso9283_test_stops_and_resumes_like_a_calibration(tmp_path: Path) -> None:
    cell = small_cell(tmp_path)
    config = load_config(cell)
    model = calibrated_model(tmp_path, cell)
    store = Store(tmp_path / CALIBRATION_DB, readonly=True)
    try:
        assert stored_kind(store, 1) == ("calibration", {})  # no kind event
        assert store.campaign(1).status == "complete"
    finally:
        store.close()
    db = str(tmp_path / "c.db")

    stop = threading.Event()

    def stop_after_three(record: Record) -> None:
        if isinstance(record, PoseStored) and record.done >= 3:
            stop.set()

    options = all_kinds()["iso9283"].read_options({"model": str(model), "cycles": 2})
    first = start_campaign(
        config,
        db,
        config_path=str(cell),
        mock=True,
        kind="iso9283",
        options=options,
        stop=stop,
        subscribers=[stop_after_three],
    )
    assert first.result is None and first.summary is None and first.kind == "iso9283"
    cid = first.campaign_id
    assert 3 <= first.acquisition.stored < len(first.plan.poses) == 20

    # Resumed from the database alone: its kind and options are stored with it.
    again = resume_campaign(db, cid)
    assert again.kind == "iso9283" and isinstance(again.result, IsoOutcome)
    assert again.result.cycles == 2 and again.summary is None
    store = Store(db, readonly=True)
    try:
        assert store.campaign(cid).status == "complete"
        assert sorted(store.completed_indices(cid)) == list(range(20))  # each exactly once
        name, stored_options = stored_kind(store, cid)
        assert (name, stored_options) == ("iso9283", options)
        assert store.has_event(cid, "iso9283")
    finally:
        store.close()

    # The command line says the same: a complete campaign is not run again; the list
    # names its kind.
    run = cellcal("run", "--resume", cid, "--db", db)
    assert run.returncode == 2 and "already complete" in run.stderr
    listed = cellcal("campaign", "list", "--db", db, "--json")
    assert {r["id"]: r["kind"] for r in json.loads(listed.stdout)["campaigns"]} == {cid: "iso9283"}


def test_unknown_kinds_and_other_kinds_options_are_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="a calibration takes no options"):
        all_kinds()["calibration"].options({"cycles": 3})
    with pytest.raises(InputError, match="takes no option 'seed'"):
        all_kinds()["iso9283"].options({"seed": 3})
    for args, words in (
        (("run", "--mock", "--kind", "drift"), "kind 'drift': one of calibration, check, iso9283"),
        (("run", "--mock", "--model", "m.toml"), "a calibration takes no options"),
        (("run", "--mock", "--kind", "iso9283"), "give --model FILE"),
        (("run", "--resume", "1", "--kind", "iso9283"), "--resume takes the campaign's kind"),
        (("run", "--mock", "--kind", "iso9283", "--model", "kuka-kr5-arc"), "calibrated model"),
    ):
        run = cellcal(*args, "--db", tmp_path / "x.db")
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert words in run.stderr
    assert not (tmp_path / "x.db").exists()
