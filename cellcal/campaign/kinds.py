"""What a campaign kind is (calibration, ISO 9283 test, …): its plan from the
configuration and its own options, what it records when it is created, and its
analysis once every pose is stored. The one runner (``runner.py``) starts, resumes,
pauses, aborts and records every kind alike; its registry, ``runner.KINDS``, names them.

A campaign's kind is stored with it as a ``kind`` event written at its creation, its
message the JSON ``{"kind": NAME, "options": {...}}``: the schema is unchanged, and a
campaign without the event (every calibration, every campaign of an earlier cellcal) is
a calibration.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from cellcal.errors import CampaignError

if TYPE_CHECKING:
    from cellcal.calib.robot_model import RobotModel
    from cellcal.campaign.analysis import CampaignSummary
    from cellcal.campaign.plan import Plan
    from cellcal.config import CellConfig
    from cellcal.store.database import Store

#: The event that stores a campaign's kind and options (not written for a calibration).
KIND_EVENT = "kind"
#: The kind of a campaign stored without a ``kind`` event.
DEFAULT_KIND = "calibration"
#: The event an ISO 9283 test of any version records at its creation.
ISO_EVENT = "iso9283"


@dataclass(frozen=True)
class Analysis:
    """A kind's analysis of a complete campaign: its result (a calibration's
    ``CampaignSummary``, an ISO 9283 test's ``IsoOutcome``) and the summary the
    campaign's end record carries (a calibration's; None for the others)."""

    result: object
    summary: CampaignSummary | None = None


class CampaignKind(Protocol):
    """One kind of campaign. Options are a JSON object; :meth:`options` checks them
    (unknown keys, types, bounds: ``InputError``) and returns their canonical form, which
    is what is stored and what :meth:`plan` and :meth:`analyse` are given."""

    @property
    def name(self) -> str: ...

    @property
    def title(self) -> str: ...

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]: ...

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        """Its options as a command line gives them (``--model FILE``, ``--cycles N``),
        with the files they name read here: what is sent to the service and stored."""
        ...

    def plan(self, config: CellConfig, options: Mapping[str, Any]) -> tuple[Plan, RobotModel]: ...

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        """The events (kind, message) it records when the campaign is created."""
        ...

    def analyse(
        self,
        store: Store,
        campaign_id: int,
        config: CellConfig,
        plan: Plan,
        nominal: RobotModel,
        options: Mapping[str, Any],
        *,
        accept: bool,
    ) -> Analysis: ...


def kind_record(name: str, options: Mapping[str, Any]) -> str:
    """The ``kind`` event's message."""
    return json.dumps({"kind": name, "options": dict(options)}, sort_keys=True)


def stored_kind(store: Store, campaign_id: int) -> tuple[str, dict[str, Any]]:
    """A stored campaign's kind and options: its ``kind`` event, else a calibration."""
    events = store.events(campaign_id)
    for e in events:
        if e["kind"] == KIND_EVENT:
            try:
                doc = json.loads(e["message"])
                name, options = doc["kind"], doc["options"]
                if not isinstance(name, str) or not isinstance(options, dict):
                    raise TypeError("not a kind and its options")
            except (ValueError, KeyError, TypeError) as exc:
                raise CampaignError(
                    f"campaign {campaign_id}: its stored kind does not read back ({exc})"
                ) from None
            return name, options
    if any(e["kind"] == ISO_EVENT for e in events):
        raise CampaignError(
            f"campaign {campaign_id} is an ISO 9283 test of an earlier cellcal, stored "
            "without its options: it cannot be resumed; run the test again"
        )
    return DEFAULT_KIND, {}
