"""A whole campaign: plan, acquire, store, register, calibrate, validate, report —
started afresh or resumed from the database."""

from __future__ import annotations

import contextlib
import hashlib
import json
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.calib.robot_model import RobotModel
from cellcal.clock import Clock, SimulatedClock, WallClock
from cellcal.config import CellConfig, config_from_dict, upgrade_stored
from cellcal.daemon.analysis import CampaignSummary, analyse
from cellcal.daemon.devices import Devices, build_devices
from cellcal.daemon.engine import Acquisition, PhaseWatcher, acquire
from cellcal.daemon.locks import RunLock, claimed_address, robot_claim
from cellcal.daemon.plan import CALIBRATION, VALIDATION, Plan, make_plan, plan_identifiability
from cellcal.daemon.plan_checks import (
    LIMITS_EVENT,
    limits_record,
    refuse_moves_outside,
    same_limits,
)
from cellcal.daemon.records import (
    CampaignEnded,
    CampaignEvent,
    CampaignStarted,
    RecordStream,
    Subscriber,
)
from cellcal.daemon.stop_request import StopRequest
from cellcal.daemon.store import Store, StoreError
from cellcal.daemon.store_devices import DEVICE_EVENT, device_message
from cellcal.daemon.store_writer import StoreWriter
from cellcal.errors import AcceptanceError, CampaignError, UserError
from cellcal.modelfiles import load_model


@dataclass(frozen=True)
class CampaignOutcome:
    campaign_id: int
    db_path: str
    config: CellConfig
    plan: Plan
    acquisition: Acquisition
    summary: CampaignSummary | None


def with_seed(config: CellConfig, seed: int | None) -> CellConfig:
    """The configuration with one seed for the simulated truth, its noise and the plan."""
    if seed is None:
        return config
    return config.model_copy(
        update={
            "simulation": config.simulation.model_copy(update={"seed": seed}),
            "campaign": config.campaign.model_copy(update={"seed": seed}),
        }
    )


def _plan(config: CellConfig) -> tuple[Plan, RobotModel]:
    nominal = load_model(config.robot.model).model
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    if len(home) != nominal.dof:
        raise CampaignError(f"robot.home_deg has {len(home)} joints, the model {nominal.dof}")
    target_offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    plan = make_plan(config.campaign, nominal, home, target_offset)
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


def note_devices(stream: RecordStream, campaign_id: int, devices: Devices) -> None:
    """Record which devices the campaign runs with, the robot first: each one's
    description (``store_devices.py``) and, for the report, the line a driver writes
    of its device when it has one (a tracker: identity and air readings)."""
    robot = getattr(devices, "robot", None)  # a holder of sensors alone (a test's) has none
    for device in (robot, *(s.sensor for s in devices.sensors)):
        describe = getattr(device, "describe", None)  # a test double may not describe
        if callable(describe):
            message = device_message(describe())
            stream.emit(CampaignEvent(campaign_id, DEVICE_EVENT, message))
        summary = getattr(device, "summary", None)
        if callable(summary):
            stream.emit(CampaignEvent(campaign_id, DEVICE_EVENT, str(summary())))


def _holder(db_path: str) -> str:
    """Who holds a robot's claim during a ``cellcal run``."""
    return f"cellcal run on {Path(db_path).resolve()}"


def config_digest(config: CellConfig) -> str:
    """A short fingerprint of the configuration a campaign runs with."""
    return hashlib.sha256(config.model_dump_json().encode()).hexdigest()[:16]


def _stream(store: Store, subscribers: Sequence[Subscriber]) -> RecordStream:
    """The campaign's record stream: the store first (critical), then the watchers."""
    stream = RecordStream()
    stream.subscribe(StoreWriter(store), critical=True)
    for subscriber in subscribers:
        stream.subscribe(subscriber)
    return stream


def _fail(
    stream: RecordStream,
    campaign_id: int,
    total: int,
    kind: str,
    message: str,
    status: str = "interrupted",
) -> None:
    """Note a failure and mark the campaign resumable (``interrupted``, or ``paused`` in
    the service) — if the database still takes writes (a full disk may not): the failure
    itself is what the user must see."""
    with contextlib.suppress(StoreError):
        stream.emit(CampaignEvent(campaign_id, kind, message))
    with contextlib.suppress(StoreError):
        stream.emit(CampaignEnded(campaign_id, status, None, total, message))


def _interrupted() -> str:
    return "interrupted"


@dataclass(frozen=True)
class Held:
    """How a campaign runs on devices someone else holds (the service): a hold request
    (deferred pause), the phase watcher (heartbeat, status page), the status a stopped
    acquisition ends in (``paused``, ``aborted``, ``interrupted``: asked when it
    stops), the status a device fault leaves it in, and the hint a failure shows."""

    hold: threading.Event | None = None
    phase: PhaseWatcher | None = None
    halted: Callable[[], str] = _interrupted
    on_fault: str = "interrupted"
    hint: str = ""


def _run(
    store: Store,
    stream: RecordStream,
    campaign_id: int,
    config: CellConfig,
    plan: Plan,
    nominal: RobotModel,
    devices: Devices,
    clock: Clock,
    *,
    stop: threading.Event | None,
    accept: bool,
    resumed: bool,
    close_devices: bool,
    held: Held | None = None,
) -> CampaignOutcome:
    held = held or Held()
    hint = held.hint or (
        f"campaign {campaign_id} is resumable: cellcal run --resume {campaign_id} --db {store.path}"
    )
    total = len(plan.poses)
    try:
        done = store.completed_indices(campaign_id)
        stream.emit(
            CampaignStarted(
                campaign_id, plan, config_digest(config), len(done), resumed, clock.now()
            )
        )
        acquisition = acquire(
            plan,
            devices.robot,
            devices.sensors,
            clock,
            campaign_id=campaign_id,
            done=done,
            stream=stream,
            dwell_s=config.campaign.dwell_s,
            samples_per_pose=config.campaign.samples_per_pose,
            speed=config.robot.speed,
            stop=stop,
            hold=held.hold,
            phase=held.phase,
        )
    except UserError as exc:
        _fail(stream, campaign_id, total, "error", f"{type(exc).__name__}: {exc}", held.on_fault)
        raise CampaignError(f"{exc}; {hint}") from exc
    except BaseException as exc:
        _fail(stream, campaign_id, total, "error", f"{type(exc).__name__}: {exc}", held.on_fault)
        raise
    finally:
        if close_devices:
            devices.close()
    n = acquisition.stored
    if acquisition.interrupted:
        status = held.halted()
        verb = "stopped" if status == "interrupted" else status
        message = f"{verb} after {n} poses"
        if isinstance(stop, StopRequest) and stop.reason:
            message += f" ({stop.reason})"
        stream.emit(CampaignEvent(campaign_id, status, message))
        stream.emit(CampaignEnded(campaign_id, status, n, total, message))
        return CampaignOutcome(campaign_id, store.path, config, plan, acquisition, None)
    try:
        summary = analyse(store, campaign_id, nominal, config.reference_sensor.name, accept=accept)
    except AcceptanceError as exc:
        stream.emit(CampaignEvent(campaign_id, "refused", str(exc)))
        stream.emit(CampaignEnded(campaign_id, "refused", n, total, str(exc)))
        raise AcceptanceError(
            exc.check,
            f"{exc.message}; every sample is stored (campaign {campaign_id} in {store.path}); "
            f"cellcal run --resume {campaign_id} --accept analyses it anyway",
        ) from exc
    except UserError as exc:
        stream.emit(CampaignEvent(campaign_id, "analysis-failed", str(exc)))
        stream.emit(CampaignEnded(campaign_id, "interrupted", n, total, str(exc)))
        raise CampaignError(f"analysis failed: {exc}; every pose is stored; {hint}") from exc
    stream.emit(CampaignEnded(campaign_id, "complete", n, total, "complete", summary))
    return CampaignOutcome(campaign_id, store.path, config, plan, acquisition, summary)


def start_campaign(
    config: CellConfig,
    db_path: str,
    *,
    config_path: str | None,
    mock: bool,
    seed: int | None = None,
    time_scale: float = 0.0,
    stop: threading.Event | None = None,
    subscribers: Sequence[Subscriber] = (),
    accept: bool = False,
    devices: Devices | None = None,
    clock: Clock | None = None,
) -> CampaignOutcome:
    """Plan, connect the devices, create a new campaign in ``db_path``, acquire and
    analyse it. Nothing is written before the plan and the devices are ready.

    ``devices`` (with the ``clock`` they take time on): devices the caller holds, which
    the campaign runs on and leaves open; by default it builds and closes its own."""
    config = with_seed(config, seed)
    plan, nominal = _plan(config)
    if clock is None:
        clock = SimulatedClock(time_scale) if mock else WallClock()
    claim = robot_claim(config, _holder(db_path), needed=not mock and devices is None)
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
            campaign_id = _create(store, config, plan, config_path, mock, time_scale, "running")
            stream = _stream(store, subscribers)
            for u in plan.unreachable:
                stream.emit(CampaignEvent(campaign_id, "unreachable", _unreachable(u)))
            note_devices(stream, campaign_id, devices)
            return _run(
                store,
                stream,
                campaign_id,
                config,
                plan,
                nominal,
                devices,
                clock,
                stop=stop,
                accept=accept,
                resumed=False,
                close_devices=own,
            )
        except BaseException:
            if own:
                with contextlib.suppress(Exception):
                    devices.close()
            raise
        finally:
            store.close()


def stored_plan(store: Store, campaign_id: int) -> tuple[CellConfig, Plan, RobotModel]:
    """A stored campaign's configuration and plan, computed again; it must come out the
    same as when the campaign was created."""
    row = store.campaign(campaign_id)
    stored = upgrade_stored(json.loads(row.config_json))
    config = config_from_dict(stored, f"campaign {campaign_id}")
    plan, nominal = _plan(config)
    if plan.digest != row.plan_digest:
        raise CampaignError(
            f"campaign {campaign_id}: the plan computed now differs from the stored one "
            "(another cellcal version or robot model?); start a new campaign"
        )
    recorded = [e["message"] for e in store.events(campaign_id) if e["kind"] == LIMITS_EVENT]
    same_limits(campaign_id, recorded, plan.limits_deg, config.robot.model)
    return config, plan, nominal


def _create(
    store: Store,
    config: CellConfig,
    plan: Plan,
    config_path: str | None,
    mock: bool,
    time_scale: float,
    status: str,
) -> int:
    """The campaign's row, with what it runs with (and the joint limits it keeps)."""
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
    )
    if plan.limits_deg:  # what a resumed campaign must keep
        store.add_event(campaign_id, LIMITS_EVENT, limits_record(plan.limits_deg), None)
    return campaign_id


def plan_campaign(config: CellConfig) -> Plan:
    """A campaign's plan (pure; refused when it cannot work), for :func:`queue_campaign`."""
    return _plan(config)[0]


def queue_campaign(
    store: Store,
    config: CellConfig,
    plan: Plan,
    *,
    config_path: str | None,
    mock: bool,
    time_scale: float,
) -> int:
    """Store a planned campaign as ``queued`` (the service runs it later with
    :func:`run_stored`)."""
    campaign_id = _create(store, config, plan, config_path, mock, time_scale, "queued")
    for u in plan.unreachable:
        store.add_event(campaign_id, "unreachable", _unreachable(u), None)
    return campaign_id


def _unreachable(u: Any) -> str:
    return f"{u.role} pose in {u.region} at {np.round(u.target_mm, 1).tolist()} mm: {u.reason}"


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
    """Run a queued campaign, or go on with a paused or interrupted one, on devices the
    caller holds (the service, which also holds the database's run lock): every pose not
    yet stored, exactly once."""
    row = store.campaign(campaign_id)
    if row.status in ("complete", "aborted"):
        raise CampaignError(f"campaign {campaign_id} is {row.status}")
    config, plan, nominal = stored_plan(store, campaign_id)
    stream = _stream(store, subscribers)
    resumed = row.status != "queued"
    if resumed:
        stored = len(store.completed_indices(campaign_id))
        stream.emit(CampaignEvent(campaign_id, "resumed", f"{stored} poses stored"))
    note_devices(stream, campaign_id, devices)
    return _run(
        store,
        stream,
        campaign_id,
        config,
        plan,
        nominal,
        devices,
        clock,
        stop=stop,
        accept=accept,
        resumed=resumed,
        close_devices=False,
        held=held,
    )


def resume_campaign(
    db_path: str,
    campaign_id: int,
    *,
    time_scale: float | None = None,
    stop: threading.Event | None = None,
    subscribers: Sequence[Subscriber] = (),
    accept: bool = False,
) -> CampaignOutcome:
    """Continue an interrupted (or refused) campaign from its last stored pose, with its stored
    configuration; the plan must come out the same."""
    if not Path(db_path).is_file():
        raise CampaignError(f"{db_path}: no such database")
    with RunLock(db_path), contextlib.ExitStack() as claims:
        store = Store(db_path)
        try:
            row = store.campaign(campaign_id)
            if row.status in ("complete", "aborted"):
                raise CampaignError(f"campaign {campaign_id} is already {row.status}")
            config, plan, nominal = stored_plan(store, campaign_id)
            held = claims.enter_context(robot_claim(config, _holder(db_path), needed=not row.mock))
            stored = len(store.completed_indices(campaign_id))
            scale = time_scale if time_scale is not None else (row.time_scale or 0.0)
            # The simulated clock goes on from the last stored pose; the noise is fresh.
            clock: Clock = (
                SimulatedClock(scale, start=store.last_pose_time(campaign_id))
                if row.mock
                else WallClock()
            )
            devices = build_devices(
                config,
                nominal,
                clock,
                mock=row.mock,
                seed=config.simulation.seed,
                noise_stream=stored,
                robot_address=claimed_address(held),
            )
            stream = _stream(store, subscribers)
            try:
                stream.emit(CampaignEvent(campaign_id, "resumed", f"{stored} poses stored"))
                note_devices(stream, campaign_id, devices)
            except BaseException:
                devices.close()
                raise
            return _run(
                store,
                stream,
                campaign_id,
                config,
                plan,
                nominal,
                devices,
                clock,
                stop=stop,
                accept=accept,
                resumed=True,
                close_devices=True,
            )
        finally:
            store.close()
