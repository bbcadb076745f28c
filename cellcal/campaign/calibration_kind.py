"""The calibration campaign as a kind (``kinds.py``): the cube's calibration poses and
the validation poses (``plan.py``), then registration, calibration and validation
(``analysis.py``). It takes no options of its own: its configuration says it all.

Light to import (the command line reads the kinds before its first line): the plan's and
the analysis' modules load when they are used."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.campaign.kinds import Acquired, Analysis, KindOption
from cellcal.config import CellConfig
from cellcal.errors import CampaignError, InputError

if TYPE_CHECKING:
    from cellcal.calib.robot_model import RobotModel
    from cellcal.campaign.plan import Plan
    from cellcal.store.database import Store


def calibration_plan(config: CellConfig) -> tuple[Plan, RobotModel]:
    """The campaign's plan and the nominal model; refused before any motion when it
    cannot work (nothing reachable, too few poses to identify, a move out of the box)."""
    from cellcal.campaign.payloads import with_payloads
    from cellcal.campaign.plan import CALIBRATION, VALIDATION, make_plan, plan_identifiability
    from cellcal.campaign.plan_checks import refuse_moves_outside
    from cellcal.campaign.reference_poses import with_reference_poses
    from cellcal.files.models import load_model

    nominal = load_model(config.robot.model).model
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    if len(home) != nominal.dof:
        raise CampaignError(f"robot.home_deg has {len(home)} joints, the model {nominal.dof}")
    target_offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    c = config.campaign
    plan = with_payloads(
        with_reference_poses(
            make_plan(c, nominal, home, target_offset), c.reference_poses, c.reference_every
        ),
        c.payloads_kg,
    )
    n_cal = plan.count(CALIBRATION)
    if n_cal == 0:
        raise CampaignError("no calibration pose of the plan is reachable; check the cube")
    if plan.count(VALIDATION) == 0:
        raise CampaignError("no validation pose of the plan is reachable")
    # Refuse before any motion a plan that cannot identify what it will need to.
    ident = plan_identifiability(nominal, plan, target_offset)
    needed = 0 if ident is None else len(ident.identified)
    if 3 * n_cal <= needed:
        raise CampaignError(
            f"{n_cal} calibration poses give {3 * n_cal} equations for {needed} identifiable "
            f"parameters; plan at least {needed // 3 + 1} (campaign.grid)"
        )
    # ... and one whose moves the safety gate would refuse on the way.
    poses = [(p.idx, p.q) for p in plan.poses]
    refuse_moves_outside(config.campaign, nominal, home, poses, target_offset)
    return plan, nominal


@dataclass(frozen=True)
class CalibrationKind:
    name: str = "calibration"
    title: str = "campaign"
    analysing: str = "every pose stored: registering, calibrating and validating…"
    command_options: tuple[KindOption, ...] = ()
    reads_database: bool = False

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        if raw:
            raise InputError(
                f"a calibration takes no options ({', '.join(sorted(raw))[:40]} given); "
                "they are for another --kind"
            )
        return {}

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        return self.options({k: v for k, v in given.items() if v is not None})

    def from_database(self, options: Mapping[str, Any], store: Store | None) -> dict[str, Any]:
        return dict(options)

    def plan(self, config: CellConfig, options: Mapping[str, Any]) -> tuple[Plan, RobotModel]:
        return calibration_plan(config)

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        return ()

    def analyse(self, done: Acquired) -> Analysis:
        from cellcal.campaign.analysis import analyse

        reference = done.config.reference_sensor.name
        summary = analyse(
            done.store,
            done.campaign_id,
            done.nominal,
            reference,
            accept=done.accept,
            terms=done.config.campaign.terms,
            payload_of={p.idx: p.payload_kg for p in done.plan.poses},
        )
        return Analysis(summary, summary)


CALIBRATION_KIND = CalibrationKind()
