"""The engine: executes a plan, pose by pose, on the devices it is handed, and emits a
record for every pose it measured and every event on the way (``records.py``).

Per pose: move → (the driver returns once the robot reports it is in position) →
dwell on the clock, waiting on the stop event → sample every sensor concurrently (a
sensor fault measures the pose again; a sensor that does not see its target —
:class:`~cellcal.errors.NoTargetError`, a broken beam — is left out of the pose, with an
event; a series short of ``samples_per_pose`` after its driver's re-takes is kept with a
``short-series`` event, another series' note becomes a ``sensor-note`` event) → emit the
pose with its raw samples (the store, a critical subscriber, writes it in one
transaction before the next move). Poses already stored (a resumed campaign) are
skipped. A stop request (Ctrl-C, SIGTERM, the service) acts at once during the dwell
and between steps: the pose under way is abandoned unstored, so the campaign stays
resumable and loses nothing. A device that fails once a stop was asked for ends the
acquisition as interrupted, not as a device fault: the pose is abandoned, not measured
again, and the failure is logged (stopping may be what made it fail). A hold request
(the service's deferred pause) lets the pose under way finish and be stored, then
stops. Every device error leaving the engine names its device (``device``: "robot", a
sensor's name). Where the robot's driver reads its joints' temperatures (a UR), each
pose records them as a ``robot-temperature`` event before it is sampled. The devices are
left open: whoever built them closes them. Whoever
watches the engine's progress (the service's heartbeat and status page) is told each
phase as it begins: ``move``, ``dwell``, ``sample``.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from cellcal.campaign.payloads import PAYLOAD_CHANGE, instruction
from cellcal.campaign.plan import Plan, PlannedPose
from cellcal.campaign.records import CampaignEvent, PoseStored, RecordStream
from cellcal.clock import Clock
from cellcal.drivers.base import ROBOT_NAME, PositionSensor, Robot, Series
from cellcal.drivers.safety import SafetyError
from cellcal.errors import DeviceError, NoTargetError, device_errors

log = logging.getLogger("cellcal.engine")

#: The event that keeps the joints' temperatures at a pose (where the robot reads them).
ROBOT_TEMPERATURE = "robot-temperature"
#: A reached joint position further than this from the plan (rad) is refused.
IN_POSITION_TOL = 1e-3
#: A sensor that fails at a pose (after its own driver's retries) is asked again this often.
SAMPLE_RETRIES = 2

#: Told each phase of a pose as it begins: (phase, the pose, the clock's time).
PhaseWatcher = Callable[[str, PlannedPose, float], None]


def _unwatched(phase: str, pose: PlannedPose, t: float) -> None:
    """No one watches the phases."""


@dataclass(frozen=True)
class SensorSetting:
    sensor: PositionSensor
    rate_hz: float


@dataclass(frozen=True)
class Acquisition:
    """How an acquisition ended: poses stored in all, stored now, interrupted or not,
    and the clock seconds it took."""

    stored: int
    stored_now: int
    interrupted: bool
    clock_seconds: float
    #: the payload (kg) the next pose needs and the robot does not carry: the acquisition
    #: stopped for the operator to mount it (``cellcal.campaign.payloads``)
    awaiting_payload: float | None = None


def acquire(
    plan: Plan,
    robot: Robot,
    sensors: Sequence[SensorSetting],
    clock: Clock,
    *,
    campaign_id: int,
    done: Collection[int],
    stream: RecordStream,
    dwell_s: float,
    samples_per_pose: int,
    speed: float,
    stop: threading.Event | None = None,
    hold: threading.Event | None = None,
    phase: PhaseWatcher | None = None,
    mounted_kg: float | None = None,
) -> Acquisition:
    """Visit every planned pose not in ``done``; see the module docstring. A pose
    planned with another payload than ``mounted_kg`` stops the acquisition with the
    instruction to mount it (a ``payload-change`` event)."""
    stop = stop or threading.Event()
    hold = hold or threading.Event()
    watch = phase or _unwatched
    todo = [p for p in plan.poses if p.idx not in done]
    total = len(plan.poses)
    t0 = clock.now()
    stored_now = 0
    interrupted = False
    awaiting: float | None = None
    with ThreadPoolExecutor(max_workers=max(1, len(sensors)), thread_name_prefix="sensor") as pool:
        for pose in todo:
            if stop.is_set() or hold.is_set():
                interrupted = True
                break
            if pose.payload_kg is not None and pose.payload_kg != mounted_kg:
                awaiting, interrupted = pose.payload_kg, True
                message = f"pose {pose.idx} is planned with another payload: " + instruction(
                    pose.payload_kg
                )
                stream.emit(
                    CampaignEvent(campaign_id, PAYLOAD_CHANGE, message, pose.idx, clock.now())
                )
                break
            try:
                record = _visit(
                    pose,
                    robot,
                    sensors,
                    clock,
                    pool,
                    stop,
                    stream,
                    campaign_id=campaign_id,
                    dwell_s=dwell_s,
                    samples_per_pose=samples_per_pose,
                    speed=speed,
                    done=len(done) + stored_now,
                    total=total,
                    phase=watch,
                )
            except DeviceError as exc:
                if stop.is_set():
                    log.info("pose %d abandoned on the stop request: %s", pose.idx, exc)
                    interrupted = True
                    break
                event = CampaignEvent(campaign_id, "device-error", str(exc), pose.idx, clock.now())
                stream.emit(event)
                raise
            if record is None:
                interrupted = True
                break
            stream.emit(record)
            stored_now += 1
    if interrupted:
        try:
            robot.stop()
        except DeviceError as exc:  # the interrupt stays one; the operator is told
            log.warning("%s: not stopped after the interrupt: %s", robot.name, exc)
    return Acquisition(len(done) + stored_now, stored_now, interrupted, clock.now() - t0, awaiting)


def _log_temperatures(
    robot: Robot, stream: RecordStream, campaign_id: int, idx: int, t: float
) -> None:
    """The joints' temperatures at the pose, as a ``robot-temperature`` event (JSON
    ``{"joints_c": [...]}``), where the robot's driver reads them (a UR)."""
    read = getattr(robot, "joint_temperatures", None)
    if read is None:
        return
    with device_errors(ROBOT_NAME):
        temps = read()
    if temps is None:
        return
    said = json.dumps({"joints_c": [round(float(v), 3) for v in temps]})
    stream.emit(CampaignEvent(campaign_id, ROBOT_TEMPERATURE, said, idx, t))


def _outcome(future: Future[Series]) -> Series | DeviceError:
    """A sensor's series, or the device error it ended with."""
    try:
        return future.result()
    except DeviceError as exc:
        return exc


def _visit(
    pose: PlannedPose,
    robot: Robot,
    sensors: Sequence[SensorSetting],
    clock: Clock,
    pool: ThreadPoolExecutor,
    stop: threading.Event,
    stream: RecordStream,
    *,
    campaign_id: int,
    dwell_s: float,
    samples_per_pose: int,
    speed: float,
    done: int,
    total: int,
    phase: PhaseWatcher,
) -> PoseStored | None:
    """One pose, measured; None if a stop request came first."""
    t_start = clock.now()
    phase("move", pose, t_start)
    # Every device error reaching the engine names its device (the drivers' do already).
    with device_errors(ROBOT_NAME):
        try:
            robot.move_joints(pose.q, speed)
        except SafetyError as exc:  # the gate knows joints, the engine which pose they are
            raise exc.at_pose(pose.idx) from None
        reached = robot.actual_joints()
    if float(np.max(np.abs(reached - pose.q))) > IN_POSITION_TOL:
        raise DeviceError(
            f"pose {pose.idx}: {robot.name}: reports {np.degrees(reached).round(3).tolist()}° "
            f"after a move to {np.degrees(pose.q).round(3).tolist()}°",
            device=ROBOT_NAME,
        )
    phase("dwell", pose, clock.now())
    if stop.is_set() or clock.wait(stop, dwell_s):
        return None
    start = clock.now()
    phase("sample", pose, start)
    _log_temperatures(robot, stream, campaign_id, pose.idx, start)

    def sample(s: SensorSetting) -> Series:
        with clock.branch(start), device_errors(s.sensor.name):
            return s.sensor.measure(samples_per_pose, s.rate_hz)

    retries = 0
    for attempt in range(SAMPLE_RETRIES + 1):
        outcomes = [_outcome(f) for f in [pool.submit(sample, s) for s in sensors]]
        faults = [
            o for o in outcomes if isinstance(o, DeviceError) and not isinstance(o, NoTargetError)
        ]
        if not faults:
            break
        if stop.is_set():
            # Stopping: the pose is abandoned rather than measured again.
            log.info("pose %d abandoned on the stop request: %s", pose.idx, faults[0])
            return None
        if attempt == SAMPLE_RETRIES:
            raise faults[0]
        # The pose is still where it should be: measure it again, once or twice.
        retries += 1
        event = CampaignEvent(campaign_id, "sensor-retry", str(faults[0]), pose.idx, clock.now())
        stream.emit(event)
        start = clock.now()
    series = [o for o in outcomes if isinstance(o, Series)]
    for got in series:
        # a series short of samples_per_pose (its driver's re-takes ran out) says so in
        # a kind of its own; a complete one with trouble on the way in a sensor-note
        short = got.n < samples_per_pose
        if got.note or short:
            why = got.note or f"{got.n} of {samples_per_pose} samples"
            message = f"pose {pose.idx}, {got.sensor}: {why}"
            kind = "short-series" if short else "sensor-note"
            stream.emit(CampaignEvent(campaign_id, kind, message, pose.idx, clock.now()))
    for s, o in zip(sensors, outcomes, strict=True):
        if isinstance(o, NoTargetError):
            # A broken beam, a target out of the cameras' view: the pose keeps what the
            # other sensors measured, and says so.
            message = f"pose {pose.idx} kept without {s.sensor.name}: {o}"
            stream.emit(CampaignEvent(campaign_id, "no-target", message, pose.idx, clock.now()))
    return PoseStored(
        campaign_id,
        pose,
        reached,
        tuple(series),
        t_start,
        clock.now(),
        retries + sum(s.retries for s in series),
        done + 1,
        total,
    )
