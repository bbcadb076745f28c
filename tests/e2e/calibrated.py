"""A calibrated simulated cell for the tests that use a campaign's results: one mock
campaign with the tracker, its report folder and the calibrated model in it."""

from __future__ import annotations

import subprocess
from pathlib import Path

from cellcal.campaign.runner import CampaignOutcome, start_campaign
from cellcal.config import CellConfig
from cellcal.reports.folder import write_report
from cellcal.store.database import Store
from tests.conftest import tracker_cell
from tests.inprocess import cellcal


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``cellcal ARGS`` in the test's process (tests/inprocess.py): its exit code and
    streams."""
    return cellcal(*args)


def calibrated_campaign(folder: Path) -> tuple[CellConfig, str, CampaignOutcome, Path]:
    """The campaign's configuration, database, outcome, and its model.toml."""
    config = tracker_cell()
    db = str(folder / "c.db")
    outcome = start_campaign(config, db, config_path=None, mock=True)
    assert outcome.summary is not None
    store = Store(db, readonly=True)
    try:
        write_report(store, outcome.campaign_id, folder / "report")
    finally:
        store.close()
    return config, db, outcome, folder / "report" / "model.toml"
