"""The one runner of every campaign kind (``kinds.py``): it starts a campaign afresh
(``cellcal run``, ``cellcal iso9283``), queues one (the service), runs a queued one or
goes on with a paused or interrupted one on devices the service holds, and resumes one
from its database (``cellcal run --resume``). Whatever the kind, the runner plans,
creates the campaign's row with its kind, acquires through the engine, records every
step on the record stream (the store first), and hands the complete campaign to the
kind's analysis; a pause, an abort, a stop or a fault ends it the same way for all.

A new kind is one module (its plan, options and analysis), listed in
``kinds.all_kinds``.

Size (about 500 lines): starting, running a queued or held campaign and resuming share
one private ``_run`` and its ending, and queueing shares ``_create`` with starting; split
apart, each would import the others' private helpers. The stored campaign's reading
(``stored_campaign``) moves out first if it grows."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.calib.robot_model import RobotModel
from cellcal.campaign.devices import Devices, build_devices
from cellcal.campaign.engine import Acquisition, acquire
from cellcal.campaign.kinds import (
    DEFAULT_KIND,
    KIND_EVENT,
    Acquired,
    CampaignKind,
    all_kinds,
    kind_named,
    kind_record,
    stored_kind,
)
from cellcal.campaign.locks import RunLock, claimed_address, robot_claim
from cellcal.campaign.payloads import PAYLOAD, instruction, mounted_payload
from cellcal.campaign.plan import Plan
from cellcal.campaign.plan_checks import LIMITS_EVENT, limits_record, same_limits
from cellcal.campaign.records import (
    CampaignEnded,
    CampaignEvent,
    CampaignStarted,
    Subscriber,
)
from cellcal.campaign.run_parts import (
    Held,
    config_digest,
    holder,
    note_devices,
    record_failure,
    record_stream,
    unreachable_text,
    with_seed,
)
from cellcal.campaign.stop_request import StopRequest
from cellcal.campaign.warm_up import warm_up
from cellcal.clock import Clock, SimulatedClock, WallClock
from cellcal.config import CellConfig, config_from_dict
from cellcal.config_earlier import upgrade_stored
from cellcal.errors import AcceptanceError, CampaignError, UserError
from cellcal.store.database import Store

if TYPE_CHECKING:
    from cellcal.campaign.analysis import CampaignSummary


@dataclass(frozen=True)
class CampaignOutcome:
    """How a run of a campaign ended: ``result`` is its kind's analysis (None when it
    stopped before its end); ``summary``, a calibration's."""

    campaign_id: int
    db_path: str
    config: CellConfig
    plan: Plan
    acquisition: Acquisition
    result: object | None
    kind: str = DEFAULT_KIND
    options: Mapping[str, Any] = field(default_factory=dict)

    @property
    def summary(self) -> CampaignSummary | None:
        from cellcal.campaign.analysis import CampaignSummary

        return self.result if isinstance(self.result, CampaignSummary) else None


@dataclass(frozen=True)
class StoredCampaign:
    """A stored campaign as it runs again: its kind and options, its configuration, and
    its plan computed again (the same as when it was created)."""

    kind: CampaignKind
    options: dict[str, Any]
    config: CellConfig
    plan: Plan
    nominal: RobotModel


@dataclass(frozen=True)
class _Asked:
    """What the caller asks of a run: a stop request, the record stream's other
    subscribers, whether a failed acceptance check is overridden, how the service holds
    it (``Held``)."""

    stop: threading.Event | None
    subscribers: Sequence[Subscriber]
    accept: bool
    held: Held = field(default_factory=Held)


def _run(
    store: Store,
    campaign_id: int,
    c: StoredCampaign,
    on: tuple[Devices, Clock],
    asked: _Asked,
    opening: Sequence[CampaignEvent],
    *,
    resumed: bool,
    close_devices: bool,
) -> CampaignOutcome:
    """Record what the campaign starts with (``opening``, then its devices), acquire
    every pose not yet stored on ``on`` (the devices and the clock they take time on),
    then the kind's analysis; every ending recorded."""
    devices, clock = on
    stream = record_stream(store, asked.subscribers)
    try:
        for event in opening:
            stream.emit(event)
        note_devices(stream, campaign_id, devices)
    except BaseException:
        if close_devices:
            devices.close()
        raise
    held, stop = asked.held, asked.stop
    hint = held.hint or (
        f"campaign {campaign_id} is resumable: cellcal run --resume {campaign_id} --db {store.path}"
    )
    config, plan = c.config, c.plan
    total = len(plan.poses)
    try:
        done = store.completed_indices(campaign_id)
        digest, now = config_digest(config), clock.now()
        stream.emit(
            CampaignStarted(campaign_id, plan, digest, len(done), resumed, now, c.kind.name)
        )
        mounted, confirmed = mounted_payload(plan, done, store.events(campaign_id))
        if mounted is not None:
            said = "mounted (the campaign resumed)" if confirmed else "on the robot"
            if confirmed or not done:
                stream.emit(CampaignEvent(campaign_id, PAYLOAD, f"{mounted:g} kg payload {said}"))
            if devices.simulated_cell is not None:  # mock mode: the operator's hands
                devices.simulated_cell.payload_kg = mounted  # type: ignore[attr-defined]
        cfg = config.campaign

        def halted() -> bool:
            return any(e is not None and e.is_set() for e in (stop, held.hold))

        warmed = len(done) == total or warm_up(
            plan,
            devices.robot,
            clock,
            stream,
            campaign_id=campaign_id,
            seconds=cfg.warm_up_s,
            settled_c_per_min=cfg.warm_up_settled_c_per_min,
            speed=config.robot.speed,
            halted=halted,
        )
        acquisition = (
            acquire(
                plan,
                devices.robot,
                devices.sensors,
                clock,
                campaign_id=campaign_id,
                done=done,
                stream=stream,
                dwell_s=cfg.dwell_s,
                samples_per_pose=cfg.samples_per_pose,
                speed=config.robot.speed,
                stop=stop,
                hold=held.hold,
                phase=held.phase,
                mounted_kg=mounted,
            )
            if warmed
            else Acquisition(len(done), 0, True, 0.0)
        )
    except BaseException as exc:
        record_failure(stream, campaign_id, total, f"{type(exc).__name__}: {exc}", held.on_fault)
        if isinstance(exc, UserError):
            raise CampaignError(f"{exc}; {hint}") from exc
        raise
    finally:
        if close_devices:
            devices.close()

    n = acquisition.stored

    def end(
        status: str, message: str, event: str | None, summary: CampaignSummary | None = None
    ) -> None:
        """The campaign's end: its ``event`` (none: None), then the end record."""
        if event is not None:
            stream.emit(CampaignEvent(campaign_id, event, message))
        stream.emit(CampaignEnded(campaign_id, status, n, total, message, summary))

    def outcome(result: object | None) -> CampaignOutcome:
        return CampaignOutcome(
            campaign_id, store.path, config, plan, acquisition, result, c.kind.name, c.options
        )

    if acquisition.awaiting_payload is not None:
        resume = (
            held.hint.split(": ", 1)[-1]
            if held.hint
            else (f"cellcal run --resume {campaign_id} --db {store.path}")
        )
        end(
            "paused",
            f"paused after {n} poses: {instruction(acquisition.awaiting_payload)} ({resume})",
            "paused",
        )
        return outcome(None)
    if acquisition.interrupted:
        status = held.halted()
        verb = "stopped" if status == "interrupted" else status
        message = f"{verb} after {n} poses"
        if isinstance(stop, StopRequest) and stop.reason:
            message += f" ({stop.reason})"
        end(status, message, status)
        return outcome(None)
    finished = Acquired(store, campaign_id, config, plan, c.nominal, c.options, asked.accept)
    try:
        analysis = c.kind.analyse(finished)
    except AcceptanceError as exc:
        end("refused", str(exc), "refused")
        raise AcceptanceError(
            exc.check,
            f"{exc.message}; every sample is stored (campaign {campaign_id} in {store.path}); "
            f"cellcal run --resume {campaign_id} --accept analyses it anyway",
        ) from exc
    except UserError as exc:
        end("interrupted", str(exc), "analysis-failed")
        raise CampaignError(f"analysis failed: {exc}; every pose is stored; {hint}") from exc
    end("complete", "complete", None, analysis.summary)
    return outcome(analysis.result)


def plan_campaign(
    config: CellConfig, kind: str = DEFAULT_KIND, options: Mapping[str, Any] | None = None
) -> tuple[Plan, dict[str, Any]]:
    """A campaign's plan (pure; refused when it cannot work) and its kind's options
    checked (completed from the database first: ``CampaignKind.from_database``), for
    :func:`queue_campaign`."""
    k = kind_named(kind)
    checked = k.options(options or {})
    return k.plan(config, checked)[0], checked


def start_campaign(
    config: CellConfig,
    db_path: str,
    *,
    config_path: str | None,
    mock: bool,
    kind: str = DEFAULT_KIND,
    options: Mapping[str, Any] | None = None,
    seed: int | None = None,
    time_scale: float = 0.0,
    stop: threading.Event | None = None,
    subscribers: Sequence[Subscriber] = (),
    accept: bool = False,
    devices: Devices | None = None,
    clock: Clock | None = None,
    planning: Callable[[], None] | None = None,
) -> CampaignOutcome:
    """Plan, connect the devices, create a new campaign of ``kind`` in ``db_path``,
    acquire and analyse it. Nothing is written before the plan and the devices are ready.

    ``devices`` (with the ``clock`` they take time on): devices the caller holds, which
    the campaign runs on and leaves open; by default it builds and closes its own.
    ``planning``: called as the planning begins, once the kind's options are settled."""
    config = with_seed(config, seed)
    k = kind_named(kind)
    checked = k.options(_completed(k, options or {}, db_path))
    if planning is not None:
        planning()
    plan, nominal = k.plan(config, checked)
    c = StoredCampaign(k, checked, config, plan, nominal)
    if clock is None:
        clock = SimulatedClock(time_scale) if mock else WallClock()
    claim = robot_claim(config, holder(db_path), needed=not mock and devices is None)
    with RunLock(db_path), claim as held:
        own = devices is None
        if devices is None:
            devices = build_devices(
                config,
                nominal,
                clock,
                mock=mock,
                seed=config.simulation.seed,
                robot_address=claimed_address(held),
            )
        try:
            store = Store(db_path)
        except BaseException:
            if own:
                devices.close()
            raise
        try:
            campaign_id = _create(
                store, k, checked, config, plan, config_path, mock, time_scale, "running"
            )
            unreachable = [
                CampaignEvent(campaign_id, "unreachable", unreachable_text(u))
                for u in plan.unreachable
            ]
            asked = _Asked(stop, subscribers, accept)
            on = (devices, clock)
            return _run(
                store, campaign_id, c, on, asked, unreachable, resumed=False, close_devices=own
            )
        except BaseException:
            if own:
                with contextlib.suppress(Exception):
                    devices.close()
            raise
        finally:
            store.close()


def _completed(k: CampaignKind, options: Mapping[str, Any], db_path: str) -> dict[str, Any]:
    """The kind's options completed from the database the campaign goes into (a check's
    current model), read-only; from none for a kind that reads none, and without a file
    yet (or the empty one a run lock leaves)."""
    file = Path(db_path)
    if not k.reads_database or not file.is_file() or file.stat().st_size == 0:
        return k.from_database(options, None)
    store = Store(db_path, readonly=True)
    try:
        return k.from_database(options, store)
    finally:
        store.close()


def stored_campaign(store: Store, campaign_id: int) -> StoredCampaign:
    """A stored campaign's kind, options, configuration and plan, computed again; the
    plan must come out the same as when the campaign was created."""
    row = store.campaign(campaign_id)
    name, raw = stored_kind(store, campaign_id)
    kinds = all_kinds()
    if name not in kinds:
        raise CampaignError(
            f"campaign {campaign_id} is of kind {name!r}, which this cellcal does not know "
            f"({', '.join(kinds)})"
        )
    kind = kinds[name]
    options = kind.options(raw)
    stored = upgrade_stored(json.loads(row.config_json))
    config = config_from_dict(stored, f"campaign {campaign_id}")
    plan, nominal = kind.plan(config, options)
    if plan.digest != row.plan_digest:
        raise CampaignError(
            f"campaign {campaign_id}: the plan computed now differs from the stored one "
            "(another cellcal version or robot model?); start a new campaign"
        )
    recorded = [e["message"] for e in store.events(campaign_id) if e["kind"] == LIMITS_EVENT]
    same_limits(campaign_id, recorded, plan.limits_deg, config.robot.model)
    return StoredCampaign(kind, options, config, plan, nominal)


def _create(
    store: Store,
    kind: CampaignKind,
    options: Mapping[str, Any],
    config: CellConfig,
    plan: Plan,
    config_path: str | None,
    mock: bool,
    time_scale: float,
    status: str,
) -> int:
    """The campaign's row, with what it runs with (its kind, the joint limits it keeps)."""
    campaign_id = store.create_campaign(
        config_json=config.model_dump_json(),
        config_path=config_path,
        mock=mock,
        seed=config.simulation.seed if mock else None,
        time_scale=time_scale if mock else None,
        model=config.robot.model,
        sensors=[s.name for s in config.sensor],
        n_poses=len(plan.poses),
        samples_per_pose=config.campaign.samples_per_pose,
        dwell_s=config.campaign.dwell_s,
        plan_digest=plan.digest,
        status=status,
        kind=kind.name,
    )
    if plan.limits_deg:  # what a resumed campaign must keep
        store.add_event(campaign_id, LIMITS_EVENT, limits_record(plan.limits_deg), None)
    if kind.name != DEFAULT_KIND:  # a campaign without it is a calibration
        store.add_event(campaign_id, KIND_EVENT, kind_record(kind.name, options), None)
    for event, message in kind.created(options):
        store.add_event(campaign_id, event, message, None)
    return campaign_id


def queue_campaign(
    store: Store,
    config: CellConfig,
    plan: Plan,
    *,
    config_path: str | None,
    mock: bool,
    time_scale: float,
    kind: str = DEFAULT_KIND,
    options: Mapping[str, Any] | None = None,
) -> int:
    """Store a planned campaign (``options``: as :func:`plan_campaign` checked them) as
    ``queued``; the service runs it later with :func:`run_stored`."""
    k = kind_named(kind)
    campaign_id = _create(
        store, k, options or {}, config, plan, config_path, mock, time_scale, "queued"
    )
    for u in plan.unreachable:
        store.add_event(campaign_id, "unreachable", unreachable_text(u), None)
    return campaign_id


def run_stored(
    store: Store,
    campaign_id: int,
    devices: Devices,
    clock: Clock,
    *,
    stop: threading.Event | None = None,
    held: Held | None = None,
    subscribers: Sequence[Subscriber] = (),
    accept: bool = False,
) -> CampaignOutcome:
    """Run a queued campaign of any kind, or go on with a paused or interrupted one, on
    devices the caller holds (the service, which also holds the database's run lock):
    every pose not yet stored, exactly once."""
    row = store.campaign(campaign_id)
    if row.status in ("complete", "aborted"):
        raise CampaignError(f"campaign {campaign_id} is {row.status}")
    c = stored_campaign(store, campaign_id)
    resumed = row.status != "queued"
    opening = []
    if resumed:
        stored = len(store.completed_indices(campaign_id))
        opening.append(CampaignEvent(campaign_id, "resumed", f"{stored} poses stored"))
    asked = _Asked(stop, subscribers, accept, held or Held())
    on = (devices, clock)
    return _run(store, campaign_id, c, on, asked, opening, resumed=resumed, close_devices=False)


def resume_campaign(
    db_path: str,
    campaign_id: int,
    *,
    time_scale: float | None = None,
    stop: threading.Event | None = None,
    subscribers: Sequence[Subscriber] = (),
    accept: bool = False,
) -> CampaignOutcome:
    """Continue an interrupted (or refused) campaign of any kind from its last stored
    pose, with its stored configuration and options; the plan must come out the same."""
    if not Path(db_path).is_file():
        raise CampaignError(f"{db_path}: no such database")
    with RunLock(db_path), contextlib.ExitStack() as claims:
        store = Store(db_path)
        try:
            row = store.campaign(campaign_id)
            if row.status in ("complete", "aborted"):
                raise CampaignError(f"campaign {campaign_id} is already {row.status}")
            c = stored_campaign(store, campaign_id)
            held = claims.enter_context(robot_claim(c.config, holder(db_path), needed=not row.mock))
            stored = len(store.completed_indices(campaign_id))
            scale = time_scale if time_scale is not None else (row.time_scale or 0.0)
            # The simulated clock goes on from the last stored pose; the noise is fresh.
            clock: Clock = (
                SimulatedClock(scale, start=store.last_pose_time(campaign_id))
                if row.mock
                else WallClock()
            )
            devices = build_devices(
                c.config,
                c.nominal,
                clock,
                mock=row.mock,
                seed=c.config.simulation.seed,
                noise_stream=stored,
                robot_address=claimed_address(held),
            )
            opening = [CampaignEvent(campaign_id, "resumed", f"{stored} poses stored")]
            asked = _Asked(stop, subscribers, accept)
            on = (devices, clock)
            return _run(store, campaign_id, c, on, asked, opening, resumed=True, close_devices=True)
        finally:
            store.close()
