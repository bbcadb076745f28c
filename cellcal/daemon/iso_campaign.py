"""The ISO 9283 pose accuracy and repeatability test as a campaign: the robot visits the
standard's five points (``calib/iso9283.py``) in turn for ``cycles`` cycles, first with
the joints its nominal model gives (what the controller does before calibration), then
with the joints the calibrated model gives (``calib/compensation.py``); every sample is
stored like any campaign's (roles ``iso-before`` / ``iso-after``, regions P1…P5), and the
result — AP and RP of each point, before and after — is the campaign's stored summary.

Positions are compared in the robot base frame of the calibrated model: the reference
sensor's means are brought there through the calibrated model's sensor frame, for both
stages (the base frame a registration of the nominal model would find is a slightly
different one, which would hide part of the nominal model's error). An interrupted test
is not resumed: run it again (its samples stay in the database).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.calib.compensation import compensate
from cellcal.calib.geometry import Array, apply, invert
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.iso9283 import PointResult, iso_points, pose_characteristics
from cellcal.calib.kinematics import target_kinematics
from cellcal.clock import SimulatedClock, WallClock
from cellcal.config import CellConfig
from cellcal.daemon.campaign import config_digest, note_devices, queue_campaign
from cellcal.daemon.devices import build_devices
from cellcal.daemon.engine import acquire
from cellcal.daemon.locks import RunLock, claimed_address, robot_claim
from cellcal.daemon.plan import Plan, PlannedPose
from cellcal.daemon.plan_checks import refuse_moves_outside
from cellcal.daemon.records import CampaignEnded, CampaignEvent, CampaignStarted, RecordStream
from cellcal.daemon.store import Store
from cellcal.daemon.store_writer import StoreWriter
from cellcal.errors import CampaignError, InputError
from cellcal.modelfiles import LoadedModel, load_model

BEFORE, AFTER = "iso-before", "iso-after"
STAGES = {BEFORE: "nominal model", AFTER: "calibrated model"}


@dataclass(frozen=True)
class IsoOutcome:
    campaign_id: int
    db_path: str
    results: dict[str, tuple[PointResult, ...]]
    #: what the report needs to say what the test was and to recompute its positions:
    #: the cycles, the nominal model (the cell's robot), the calibrated model given, the
    #: reference sensor and its frame in the calibrated model (4×4, mm)
    cycles: int = 0
    nominal_model: str = ""
    calibrated_model: str = ""
    reference_sensor: str = ""
    T_sensor_base: Array | None = None

    def to_dict(self) -> dict[str, Any]:
        def point(r: PointResult) -> dict[str, Any]:
            return {
                "point": r.name,
                "commanded_mm": r.commanded.tolist(),
                "barycentre_mm": r.barycentre.tolist(),
                "ap_mm": r.ap,
                "ap_xyz_mm": r.ap_xyz.tolist(),
                "rp_mm": r.rp,
                "l_mean_mm": r.l_mean,
                "s_l_mm": r.l_std,
                "n": r.n,
            }

        return {
            "campaign_id": self.campaign_id,
            "test": "ISO 9283 pose accuracy and repeatability",
            "cycles": self.cycles,
            "nominal_model": self.nominal_model,
            "calibrated_model": self.calibrated_model,
            "reference_sensor": self.reference_sensor,
            "T_sensor_base": None if self.T_sensor_base is None else self.T_sensor_base.tolist(),
            "iso9283": {
                stage: {"joints_from": STAGES[stage], "points": [point(r) for r in rs]}
                for stage, rs in self.results.items()
            },
        }


def iso_plan(config: CellConfig, calibrated: LoadedModel, cycles: int) -> Plan:
    """Both stages' poses: the five points, ``cycles`` times, with the flange held at the
    orientation it has at the robot's home."""
    if cycles < 2:
        raise InputError(f"--cycles {cycles}: AP and RP need at least 2 cycles (ISO 9283: 30)")
    nominal = load_model(config.robot.model).model
    if nominal.dof != calibrated.model.dof:
        raise InputError(
            f"the calibrated model has {calibrated.model.dof} joints, the cell's robot "
            f"{config.robot.model} {nominal.dof}"
        )
    tool = calibrated.tool
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    R0 = target_kinematics(nominal, home[None], tool, jacobian=False).R_flange[0]
    points = iso_points(np.asarray(config.campaign.cube_centre_mm), config.campaign.cube_edge_mm)
    before = solve(nominal, tool, points, R0, home)
    after = compensate(
        calibrated.model, tool, nominal, points, np.broadcast_to(R0, (5, 3, 3)), before.q
    )
    if not (before.ok.all() and after.ok.all()):
        raise InputError(
            "an ISO 9283 point of the cube (campaign.cube_centre_mm, cube_edge_mm) has no "
            "joint solution within the limits"
        )
    poses: list[PlannedPose] = []
    for role, q in ((BEFORE, before.q), (AFTER, after.q)):
        for _ in range(cycles):
            for k in range(5):
                poses.append(PlannedPose(len(poses), role, f"P{k + 1}", points[k], q[k]))
    # The moves as the safety gate will check them (its target: the reference sensor's).
    gate_offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    moves = [(p.idx, p.q) for p in poses]
    refuse_moves_outside(config.campaign, nominal, home, moves, gate_offset)
    return Plan(tuple(poses), ())


def run_iso9283(
    config: CellConfig,
    db_path: str,
    model_spec: str,
    *,
    mock: bool,
    cycles: int,
    config_path: str | None = None,
    time_scale: float = 0.0,
) -> IsoOutcome:
    """Run the test on the configured cell (or its twins) and store it in ``db_path``."""
    calibrated = load_model(model_spec)
    if not calibrated.calibrated or calibrated.T_sensor_base is None:
        raise InputError(f"--model {model_spec}: the test compares against a calibrated model")
    plan = iso_plan(config, calibrated, cycles)
    nominal = load_model(config.robot.model).model
    reference = config.reference_sensor.name
    clock = SimulatedClock(time_scale) if mock else WallClock()
    holder = f"cellcal iso9283 on {Path(db_path).resolve()}"
    with RunLock(db_path), robot_claim(config, holder, needed=not mock) as held:
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
            try:
                cid = queue_campaign(
                    store, config, plan, config_path=config_path, mock=mock, time_scale=time_scale
                )
                store.set_status(cid, "running")
                stream = RecordStream()
                stream.subscribe(StoreWriter(store), critical=True)
                stream.emit(
                    CampaignEvent(cid, "iso9283", f"{cycles} cycles, joints from {model_spec}")
                )
                note_devices(stream, cid, devices)
                stream.emit(
                    CampaignStarted(cid, plan, config_digest(config), 0, False, clock.now())
                )
                acq = acquire(
                    plan,
                    devices.robot,
                    devices.sensors,
                    clock,
                    campaign_id=cid,
                    done=set(),
                    stream=stream,
                    dwell_s=config.campaign.dwell_s,
                    samples_per_pose=config.campaign.samples_per_pose,
                    speed=config.robot.speed,
                )
                total = len(plan.poses)
                if acq.interrupted:
                    message = f"stopped after {acq.stored} poses; run the test again"
                    stream.emit(CampaignEnded(cid, "interrupted", acq.stored, total, message))
                    raise CampaignError(f"ISO 9283 test {message}")
                points = np.array([p.target_mm for p in plan.poses[:5]])
                results = _results(store, cid, reference, calibrated.T_sensor_base, cycles, points)
                outcome = IsoOutcome(
                    cid,
                    db_path,
                    results,
                    cycles=cycles,
                    nominal_model=config.robot.model,
                    calibrated_model=_spec_text(model_spec),
                    reference_sensor=reference,
                    T_sensor_base=np.asarray(calibrated.T_sensor_base, dtype=np.float64),
                )
                store.add_report(cid, outcome.to_dict())
                stream.emit(CampaignEnded(cid, "complete", acq.stored, total, "complete"))
                return outcome
            finally:
                store.close()
        finally:
            devices.close()


def _spec_text(spec: str) -> str:
    """A model given as a file, by its absolute path (the report says which)."""
    path = Path(spec)
    return str(path.resolve()) if path.is_file() else spec


def _results(
    store: Store, cid: int, reference: str, T_sensor_base: Array, cycles: int, points: Array
) -> dict[str, tuple[PointResult, ...]]:
    data = store.pose_data(cid)
    if reference not in data.mean:
        raise CampaignError(
            f"ISO 9283 test {cid}: the reference sensor {reference} measured nothing"
        )
    T_base_sensor = invert(T_sensor_base)
    out = {}
    for stage in (BEFORE, AFTER):
        rows = [k for k, r in enumerate(data.role) if r == stage]
        m = data.mean[reference][rows]
        if not np.isfinite(m).all():
            raise CampaignError(
                f"ISO 9283 test {cid}: the reference sensor missed poses; run the test again"
            )
        attained = apply(T_base_sensor, m).reshape(cycles, 5, 3)
        out[stage] = pose_characteristics(points, attained)
    return out
