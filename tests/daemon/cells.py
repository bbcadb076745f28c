"""A calibrated model of the small cell's simulated robot (``conftest.small_cell``), for
the tests of the campaigns that need one (the ISO 9283 test, as a kind of the runner
and in the service)."""

from __future__ import annotations

from pathlib import Path

from cellcal.campaign.runner import start_campaign
from cellcal.config import load_config
from cellcal.store.database import Store

#: The database, in the test's folder, of the calibration :func:`calibrated_model` runs.
CALIBRATION_DB = "cal.db"


def calibrated_model(folder: Path, cell: Path) -> Path:
    """A calibration of ``cell``'s simulated robot (campaign 1 of ``folder/cal.db``), its
    calibrated model written to ``folder/model.toml``."""
    db = str(folder / CALIBRATION_DB)
    out = start_campaign(load_config(cell), db, config_path=str(cell), mock=True)
    store = Store(db, readonly=True)
    try:
        text = store.latest_model_toml(out.campaign_id)
    finally:
        store.close()
    assert text is not None
    path = folder / "model.toml"
    path.write_text(text, encoding="utf-8")
    return path
