"""What a campaign kind is (calibration, ISO 9283 test, …): its plan from the
configuration and its own options, its command-line options, what it records when it is
created, and its analysis once every pose is stored. The one runner (``runner.py``)
starts, resumes, pauses, aborts and records every kind alike; :func:`all_kinds` names
them, and ``cellcal run`` and ``cellcal campaign start`` make their ``--kind`` and each
kind's options from it.

A campaign's kind is stored with it as a ``kind`` event written at its creation, its
message the JSON ``{"kind": NAME, "options": {...}}``: the schema is unchanged, and a
campaign without the event (every calibration, every campaign of an earlier cellcal) is
a calibration.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from cellcal.errors import CampaignError, InputError

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
class KindOption:
    """One of a kind's options as a command line gives it, ``--NAME``: ``cellcal run`` and
    ``cellcal campaign start`` add every kind's to theirs, and the kind's
    :meth:`~CampaignKind.read_options` is given their values by name (None: not given).

    ``help`` follows ``--kind KIND:`` in the option's help; ``sent``, where it differs,
    replaces it in ``campaign start`` (whose client reads what the option names and sends
    it). The value is a whole number from ``low`` to ``high`` when both are given, else
    a text (a file's name); ``default`` is the kind's value when it is not given."""

    name: str
    help: str
    low: int | None = None
    high: int | None = None
    default: int | str | None = None
    sent: str | None = None

    def accepts(self, value: object) -> bool:
        """Whether ``value`` is one of the option's (a JSON boolean is not a number)."""
        if self.low is None or self.high is None:
            return isinstance(value, str)
        if isinstance(value, bool) or not isinstance(value, int):
            return False
        return self.low <= value <= self.high


@dataclass(frozen=True)
class Acquired:
    """A campaign every pose of which is stored, as its kind's analysis is handed it: where
    it is (``store``, ``campaign_id``), what it ran with (the configuration, the plan, the
    nominal model, its kind's options), and whether a failed acceptance check is
    overridden (``accept``)."""

    store: Store
    campaign_id: int
    config: CellConfig
    plan: Plan
    nominal: RobotModel
    options: Mapping[str, Any]
    accept: bool = False


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

    @property
    def analysing(self) -> str:
        """What follows the last pose, said as it begins (a command's progress)."""
        ...

    @property
    def command_options(self) -> tuple[KindOption, ...]:
        """Its options on the command line (none: it takes none)."""
        ...

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]: ...

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        """Its options as a command line gives them (``--model FILE``, ``--cycles N``),
        with the files they name read here: what is sent to the service and stored."""
        ...

    @property
    def reads_database(self) -> bool:
        """Whether :meth:`from_database` reads the database (else it is not opened for it:
        opening checks every page of the file)."""
        ...

    def from_database(self, options: Mapping[str, Any], store: Store | None) -> dict[str, Any]:
        """Its options completed from the database the campaign goes into (``store``;
        None: there is none yet) before they are checked: a check's current model when
        none is given. The other kinds' come back unchanged."""
        ...

    def plan(self, config: CellConfig, options: Mapping[str, Any]) -> tuple[Plan, RobotModel]: ...

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        """The events (kind, message) it records when the campaign is created."""
        ...

    def analyse(self, done: Acquired) -> Analysis: ...


@functools.cache
def all_kinds() -> dict[str, CampaignKind]:
    """Every campaign kind, by the name it is stored and asked for with (``--kind``): a
    new kind is one module, imported and listed here. (Imported here, not at the top:
    each kind's module imports this one. A kind's module is light to import — its plan
    and analysis load when used —, for ``cellcal run`` builds its options from this
    table before it says its first line.)"""
    from cellcal.campaign.calibration_kind import CALIBRATION_KIND
    from cellcal.campaign.check_kind import CHECK_KIND
    from cellcal.campaign.iso9283_kind import ISO9283_KIND

    return {k.name: k for k in (CALIBRATION_KIND, CHECK_KIND, ISO9283_KIND)}


#: ``--model FILE``, as the kinds that compare with a calibrated model take it (the ISO 9283
#: test, the check): read on the command line, its text sent and stored
CALIBRATED_MODEL = KindOption(
    "model",
    "the calibrated model (model.toml).",
    sent="the calibrated model (its text is sent).",
)


def refuse_other_options(title: str, own: Sequence[KindOption], given: Mapping[str, Any]) -> None:
    """A command line's options of another kind (given, not None) refused in one line,
    naming the kind's own (``title``: ``a check``, ``an ISO 9283 test``)."""
    names = [o.name for o in own]
    other = sorted(k for k, v in given.items() if v is not None and k not in names)
    if other:
        raise InputError(
            f"{title} takes no option --{other[0][:40]} (it takes "
            f"{', '.join('--' + o for o in names)}); it is for another --kind"
        )


def model_label(spec: str) -> str:
    """A model given as a file, by its absolute path (what a report says it used)."""
    from pathlib import Path

    path = Path(spec)
    return str(path.resolve()) if path.is_file() else spec


def kind_named(name: str) -> CampaignKind:
    kinds = all_kinds()
    if name not in kinds:
        shown = repr(name) if len(repr(name)) <= 40 else repr(name)[:39] + "…"
        raise InputError(f"kind {shown}: one of {', '.join(kinds)}")
    return kinds[name]


def kind_record(name: str, options: Mapping[str, Any]) -> str:
    """The ``kind`` event's message."""
    return json.dumps({"kind": name, "options": dict(options)}, sort_keys=True)


def stored_kind(store: Store, campaign_id: int) -> tuple[str, dict[str, Any]]:
    """A stored campaign's kind and options: its ``kind`` event, else a calibration."""
    first = store.first_events((KIND_EVENT, ISO_EVENT), campaign_id).get(campaign_id, {})
    if KIND_EVENT in first:
        try:
            return _kind_and_options(first[KIND_EVENT])
        except (ValueError, KeyError, TypeError) as exc:
            raise CampaignError(
                f"campaign {campaign_id}: its stored kind does not read back ({exc})"
            ) from None
    if ISO_EVENT in first:
        raise CampaignError(
            f"campaign {campaign_id} is an ISO 9283 test of an earlier cellcal, stored "
            "without its options: it cannot be resumed; run the test again"
        )
    return DEFAULT_KIND, {}


def shown_kinds(store: Store, campaign_id: int | None = None) -> dict[int, str]:
    """The kind of every campaign (or of ``campaign_id`` alone) as the campaign list and
    the status show it: :func:`stored_kind`'s name, an ``iso9283`` for an ISO 9283 test of
    an earlier cellcal (its ``iso9283`` event alone), and ``unknown`` for a ``kind``
    event that does not read back as a kind's name (never a refusal: it is only shown).
    A campaign missing from the answer is a calibration."""
    shown = {}
    for cid, first in store.first_events((KIND_EVENT, ISO_EVENT), campaign_id).items():
        if KIND_EVENT not in first:
            shown[cid] = ISO_EVENT  # the ISO 9283 test's kind has its event's name
            continue
        try:
            name = _kind_and_options(first[KIND_EVENT])[0]
        except (ValueError, KeyError, TypeError):
            name = ""
        ok = 0 < len(name) <= 40 and name.isascii() and name.replace("-", "").isalnum()
        shown[cid] = name if ok else "unknown"
    return shown


def _kind_and_options(message: str) -> tuple[str, dict[str, Any]]:
    """A ``kind`` event's kind and options (ValueError, KeyError, TypeError: it is not one)."""
    doc = json.loads(message)
    name, options = doc["kind"], doc["options"]
    if not isinstance(name, str) or not isinstance(options, dict):
        raise TypeError("not a kind and its options")
    return name, options
