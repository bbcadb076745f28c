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
is resumed like any campaign (``cellcal run --resume``), its kind and options read back.

Light to import (the command line reads the kinds and their options before its first
line): inverse kinematics, the plan's modules and the model files load when used.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.calib.geometry import Array, apply, invert
from cellcal.calib.iso9283 import CYCLES, PointResult, iso_points, pose_characteristics
from cellcal.calib.kinematics import target_kinematics
from cellcal.campaign.kinds import (
    CALIBRATED_MODEL,
    ISO_EVENT,
    Acquired,
    Analysis,
    KindOption,
    model_label,
    refuse_other_options,
)
from cellcal.config import CellConfig
from cellcal.errors import CampaignError, InputError
from cellcal.files.text import read_text

if TYPE_CHECKING:
    from cellcal.calib.robot_model import RobotModel
    from cellcal.campaign.plan import Plan
    from cellcal.files.models import LoadedModel
    from cellcal.store.database import Store

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
    from cellcal.calib.compensation import compensate
    from cellcal.calib.inverse_kinematics import solve
    from cellcal.campaign.plan import Plan, PlannedPose
    from cellcal.campaign.plan_checks import refuse_moves_outside
    from cellcal.files.models import load_model

    if cycles < 2:
        raise InputError(f"--cycles {cycles}: AP and RP need at least 2 cycles (ISO 9283: 30)")
    nominal = load_model(config.robot.model).model
    if nominal.dof != calibrated.model.dof:
        raise InputError(
            f"the calibrated model has {calibrated.model.dof} joints, the cell's robot "
            f"{config.robot.model} {nominal.dof}"
        )
    target_offset = calibrated.target_offset
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    R0 = target_kinematics(nominal, home[None], target_offset, jacobian=False).R_flange[0]
    points = iso_points(np.asarray(config.campaign.cube_centre_mm), config.campaign.cube_edge_mm)
    before = solve(nominal, target_offset, points, R0, home)
    after = compensate(
        calibrated.model, target_offset, nominal, points, np.broadcast_to(R0, (5, 3, 3)), before.q
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


def iso_options(model_spec: str, cycles: int) -> dict[str, Any]:
    """The test's options from the command line: the calibrated model named by
    ``model_spec`` (read here: its text goes with the campaign) and the cycles."""
    from cellcal.files.models import load_model

    calibrated = load_model(model_spec)
    if not calibrated.calibrated or calibrated.T_sensor_base is None:
        raise InputError(f"--model {model_spec}: the test compares against a calibrated model")
    text = read_text(model_spec, "a calibrated model")
    return {"cycles": cycles, "model": model_label(model_spec), "model_toml": text}


#: The options of an ISO 9283 test (``--cycles``, ``--model``): the calibrated model's
#: text and the name it is known by (a file's absolute path).
OPTIONS = ("cycles", "model", "model_toml")
#: ... as the command line gives them: the calibrated model's file, read there (its text
#: is sent to the service), and the cycles.
MODEL = CALIBRATED_MODEL
CYCLE_COUNT = KindOption(
    "cycles", f"cycles (the standard: {CYCLES}).", low=2, high=1000, default=CYCLES
)


def _calibrated(options: Mapping[str, Any]) -> LoadedModel:
    from cellcal.files.models import model_from_text

    label = str(options.get("model") or "the calibrated model")
    calibrated = model_from_text(str(options["model_toml"]), label)
    if not calibrated.calibrated or calibrated.T_sensor_base is None:
        raise InputError(f"--model {label}: the test compares against a calibrated model")
    return calibrated


@dataclass(frozen=True)
class Iso9283Kind:
    """The ISO 9283 test as a campaign kind (``kinds.py``)."""

    name: str = "iso9283"
    title: str = "ISO 9283 test"
    analysing: str = "every visit stored: computing AP and RP, before and after…"
    command_options: tuple[KindOption, ...] = (MODEL, CYCLE_COUNT)
    reads_database: bool = False

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(raw) - set(OPTIONS))
        if unknown:
            raise InputError(
                f"an ISO 9283 test takes no option {unknown[0][:40]!r} (it takes "
                f"{', '.join(OPTIONS)})"
            )
        cycles = raw.get("cycles", CYCLE_COUNT.default)
        if not CYCLE_COUNT.accepts(cycles):
            raise InputError(
                f"cycles {str(cycles)[:40]}: a whole number from {CYCLE_COUNT.low} to "
                f"{CYCLE_COUNT.high} (AP and RP need at least 2 cycles; ISO 9283: {CYCLES})"
            )
        text, label = raw.get("model_toml"), raw.get("model", "the calibrated model")
        if not isinstance(text, str) or not text:
            raise InputError("an ISO 9283 test needs the calibrated model (--model, model_toml)")
        if not isinstance(label, str) or any(not c.isprintable() for c in label):
            raise InputError("model must be one line of text (the calibrated model's name)")
        options = {"cycles": cycles, "model": label, "model_toml": text}
        _calibrated(options)  # it must read as a calibrated model
        return options

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        refuse_other_options("an ISO 9283 test", self.command_options, given)
        spec = given.get(MODEL.name)
        if spec is None:
            raise InputError("an ISO 9283 test needs the calibrated model: give --model FILE")
        cycles = given.get(CYCLE_COUNT.name)
        return iso_options(str(spec), CYCLES if cycles is None else int(cycles))

    def from_database(self, options: Mapping[str, Any], store: Store | None) -> dict[str, Any]:
        return dict(options)

    def plan(self, config: CellConfig, options: Mapping[str, Any]) -> tuple[Plan, RobotModel]:
        from cellcal.files.models import load_model

        plan = iso_plan(config, _calibrated(options), int(options["cycles"]))
        return plan, load_model(config.robot.model).model

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        return ((ISO_EVENT, f"{options['cycles']} cycles, joints from {options['model']}"),)

    def analyse(self, done: Acquired) -> Analysis:
        calibrated = _calibrated(done.options)
        assert calibrated.T_sensor_base is not None  # _calibrated refuses any other
        cycles = int(done.options["cycles"])
        reference = done.config.reference_sensor.name
        points = np.array([p.target_mm for p in done.plan.poses[:5]])
        T = np.asarray(calibrated.T_sensor_base, dtype=np.float64)
        results = _results(done.store, done.campaign_id, reference, T, cycles, points)
        outcome = IsoOutcome(
            done.campaign_id,
            done.store.path,
            results,
            cycles=cycles,
            nominal_model=done.config.robot.model,
            calibrated_model=str(done.options["model"]),
            reference_sensor=reference,
            T_sensor_base=T,
        )
        done.store.add_report(done.campaign_id, outcome.to_dict())
        return Analysis(outcome, None)


ISO9283_KIND = Iso9283Kind()


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
