"""A calibration campaign: plan, acquire, store, register, calibrate, validate, report —
started afresh or resumed from the database. The work is the one runner's
(``runner.py``), which runs every campaign kind alike; this module keeps the names the
calibration campaign has always had (``start_campaign``, ``resume_campaign``,
``run_stored``, ``queue_campaign``, ``plan_campaign``, ``stored_plan``)."""

from __future__ import annotations

from cellcal.calib.robot_model import RobotModel
from cellcal.config import CellConfig
from cellcal.daemon.calibration_kind import calibration_plan
from cellcal.daemon.plan import Plan
from cellcal.daemon.run_parts import Held, config_digest, note_devices, with_seed
from cellcal.daemon.runner import (
    KINDS,
    CampaignOutcome,
    queue_campaign,
    resume_campaign,
    run_stored,
    start_campaign,
    stored_campaign,
)
from cellcal.daemon.store import Store

__all__ = [
    "KINDS",
    "CampaignOutcome",
    "Held",
    "config_digest",
    "note_devices",
    "plan_campaign",
    "queue_campaign",
    "resume_campaign",
    "run_stored",
    "start_campaign",
    "stored_plan",
    "with_seed",
]


def plan_campaign(config: CellConfig) -> Plan:
    """A calibration campaign's plan (pure; refused when it cannot work), for
    :func:`queue_campaign`."""
    return calibration_plan(config)[0]


def stored_plan(store: Store, campaign_id: int) -> tuple[CellConfig, Plan, RobotModel]:
    """A stored campaign's configuration and plan, computed again; it must come out the
    same as when the campaign was created."""
    c = stored_campaign(store, campaign_id)
    return c.config, c.plan, c.nominal
