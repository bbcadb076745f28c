"""The check between calibrations as a campaign kind (``kinds.py``): a few poses
measured with the same devices, dwell and samples as a calibration, compared with the
robot's current model (``calib/drift.py``: errors, limits, verdict, cause).

**Which model.** ``--model FILE``, or the cell's current model: the latest one the
database holds as valid (``store/validity.py``), resolved when the check is created and
stored with its options (its text, id and digest), so that a resumed check compares with
the same model. A check never writes a model; a check that says ``recalibrate`` ends
the validity of the database's model it checked.

**Which poses.** Candidates drawn uniformly in the cube (the region the model was
calibrated for and the robot works in), the wrist turned at random up to the campaign's
``orientation_variation_deg`` about each axis as the calibration's poses are (farther,
the model extrapolates and its error grows beyond what it predicts), from a seed of
their own — positions off the calibration grid, so that no calibration pose is measured
again —, solved by inverse kinematics of the nominal model; of the reachable ones, the
``[check] poses`` (default 12) that are D-optimal for what drifts: every joint's offset
and the sensor frame (the robot's base), through the calibrated model's Jacobian, in a
short tour from home.

Light to import (the command line reads the kinds before its first line).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.campaign.kinds import (
    CALIBRATED_MODEL,
    Acquired,
    Analysis,
    KindOption,
    model_label,
    refuse_other_options,
)
from cellcal.check_config import MAX_POSES, MIN_POSES
from cellcal.config import CellConfig
from cellcal.errors import CampaignError, InputError
from cellcal.files.text import read_text

if TYPE_CHECKING:
    from cellcal.calib.drift import Diagnosis, Limits
    from cellcal.calib.geometry import Array
    from cellcal.calib.robot_model import RobotModel
    from cellcal.campaign.plan import Plan
    from cellcal.files.models import LoadedModel
    from cellcal.store.database import Store

CHECK = "check"
#: candidates drawn in the cube (their wrist turned as the calibration's poses are)
CANDIDATES = 300
#: the candidates' own seed stream (the calibration's cube uses [seed], [seed, 1], [seed, 2])
SEED_STREAM = 3
OPTIONS = ("poses", "model", "model_toml", "model_id")

POSES = KindOption(
    "poses",
    f"poses (default: [check] poses, 12; {MIN_POSES} to {MAX_POSES}).",
    low=MIN_POSES,
    high=MAX_POSES,
)
MODEL = CALIBRATED_MODEL


@dataclass(frozen=True)
class CheckOutcome:
    """A check's result: per pose its error (mm), the RMS and largest, the limits, the
    verdict and the cause; the model it compared with (its name, database id — None for
    a file — and digest)."""

    campaign_id: int
    db_path: str
    model: str
    model_id: int | None
    model_digest: str
    errors_mm: tuple[float, ...]
    rms_mm: float
    max_mm: float
    limits: Limits
    verdict: str
    diagnosis: Diagnosis
    reference_sensor: str = ""

    @property
    def cause(self) -> str | None:
        return self.diagnosis.sentence

    def to_dict(self) -> dict[str, Any]:
        lim = self.limits
        d = self.diagnosis
        return {
            "campaign_id": self.campaign_id,
            "kind": CHECK,
            "model": self.model,
            "model_id": self.model_id,
            "model_digest": self.model_digest,
            "reference_sensor": self.reference_sensor,
            "n_poses": len(self.errors_mm),
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "warning_mm": lim.warning_mm,
            "limit_mm": lim.limit_mm,
            "predicted_mm": lim.predicted_mm,
            "validation_mm": lim.validation_mm,
            "earlier_checks_mm": lim.earlier_mm,
            "earlier_checks": lim.n_earlier,
            "verdict": self.verdict,
            "cause": self.cause,
            "causes": [
                {
                    "name": c.name,
                    "text": c.text,
                    "values": c.values,
                    "explained": c.explained,
                    "left_mm": c.left_mm,
                }
                for c in ((d.cause, *d.alternatives) if d.cause else ())
            ],
            "errors_mm": list(self.errors_mm),
        }


def check_model(options: Mapping[str, Any]) -> LoadedModel:
    from cellcal.files.models import model_from_text

    label = str(options.get("model") or "the model")
    loaded = model_from_text(str(options["model_toml"]), label)
    if not loaded.calibrated or loaded.T_sensor_base is None:
        raise InputError(f"--model {label}: a check compares with a calibrated model")
    return loaded


def check_plan(config: CellConfig, calibrated: LoadedModel, n: int) -> Plan:
    """The check's poses (see the module's text)."""
    from cellcal.calib.error_model import State, jacobian, parameter_specs
    from cellcal.calib.kinematics import target_kinematics
    from cellcal.calib.pose_selection import d_optimal, nearest_neighbour_order
    from cellcal.campaign.plan import Plan, PlannedPose, solve_group
    from cellcal.campaign.plan_checks import refuse_moves_outside
    from cellcal.campaign.plan_region import orientations
    from cellcal.files.models import load_model

    nominal = load_model(config.robot.model).model
    if nominal.dof != calibrated.model.dof:
        raise InputError(
            f"the model has {calibrated.model.dof} joints, the cell's robot "
            f"{config.robot.model} {nominal.dof}"
        )
    cfg = config.campaign
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    rng = np.random.default_rng([cfg.seed, SEED_STREAM])
    h = cfg.cube_edge_mm / 2.0
    points = np.asarray(cfg.cube_centre_mm) + rng.uniform(-h, h, (CANDIDATES, 3))
    R0 = target_kinematics(nominal, home[None], offset, jacobian=False).R_flange[0]
    turn = cfg.orientation_variation_deg
    q, ok = solve_group(nominal, home, offset, R0, points, orientations(rng, R0, CANDIDATES, turn))
    if int(ok.sum()) < n:
        raise InputError(
            f"{int(ok.sum())} of {CANDIDATES} check candidates in the cube are reachable, "
            f"{n} poses asked for; check the cube (campaign.cube_centre_mm, cube_edge_mm)"
        )
    q, points = q[ok], points[ok]
    _same_robot(config, nominal, calibrated, q, offset)
    # what drifts: every joint's offset and the sensor frame (the robot's base)
    T = np.asarray(calibrated.T_sensor_base, dtype=np.float64)
    state = State(calibrated.model, calibrated.target_offset, T[:3, :3], T[:3, 3], np.zeros(3))
    specs = tuple(
        s
        for s in parameter_specs(calibrated.model)
        if s.kind in ("theta", "frame_rot", "frame_trans")
    )
    _, J = jacobian(state, q, specs)
    J = J / np.linalg.norm(J.reshape(-1, len(specs)), axis=0)
    chosen = list(d_optimal(J, n).chosen)
    order = nearest_neighbour_order(q[chosen], home)
    poses = tuple(
        PlannedPose(i, CHECK, "cube", points[chosen[k]], q[chosen[k]]) for i, k in enumerate(order)
    )
    refuse_moves_outside(cfg, nominal, home, [(p.idx, p.q) for p in poses], offset)
    return Plan(poses, ())


def _same_robot(
    config: CellConfig, nominal: RobotModel, calibrated: LoadedModel, q: Array, offset: Array
) -> None:
    """Refused before any motion: a model that is not a calibration of the cell's robot
    (a database or a file of another cell), whose target would be more than a
    calibration's largest correction away from the nominal one's at the check's poses."""
    from cellcal.calib.compensation import MAX_CORRECTION_MM
    from cellcal.calib.kinematics import target_kinematics

    at = target_kinematics(nominal, q, offset, jacobian=False).p
    apart = target_kinematics(calibrated.model, q, offset, jacobian=False).p - at
    far = float(np.max(np.linalg.norm(apart, axis=1)))
    if far > MAX_CORRECTION_MM:
        raise InputError(
            f"the model is not a calibration of this cell's robot ({config.robot.model}): "
            f"its target is up to {far:.0f} mm from the nominal model's at the check's "
            f"poses, a calibration moves it at most {MAX_CORRECTION_MM:g} mm; give this "
            "cell's database (--db) or its model (--model)"
        )


@dataclass(frozen=True)
class CheckKind:
    """The check as a campaign kind (``kinds.py``)."""

    name: str = CHECK
    title: str = "check"
    analysing: str = "every pose stored: comparing the errors with the model's limits…"
    command_options: tuple[KindOption, ...] = (MODEL, POSES)
    reads_database: bool = True

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(raw) - set(OPTIONS))
        if unknown:
            raise InputError(
                f"a check takes no option {unknown[0][:40]!r} (it takes {', '.join(OPTIONS)})"
            )
        poses = raw.get("poses")
        if poses is not None and not POSES.accepts(poses):
            raise InputError(
                f"poses {str(poses)[:40]}: a whole number from {MIN_POSES} to {MAX_POSES}"
            )
        text, label, mid = raw.get("model_toml"), raw.get("model"), raw.get("model_id")
        if not isinstance(text, str) or not text:
            raise InputError(
                "a check needs the model it compares with: the database's current model, "
                "or --model FILE"
            )
        if not isinstance(label, str) or not label or any(not c.isprintable() for c in label):
            raise InputError("model must be one line of text (the model's name)")
        if mid is not None and (isinstance(mid, bool) or not isinstance(mid, int)):
            raise InputError("model_id must be a whole number (the database's model id)")
        from cellcal.files.models import model_uncertainty

        options = {"poses": poses, "model": label, "model_toml": text, "model_id": mid}
        check_model(options)  # it must read as a calibrated model, before any motion,
        model_uncertainty(text, label)  # with what the limits are computed from
        return options

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        refuse_other_options("a check", self.command_options, given)
        out: dict[str, Any] = {"poses": given.get(POSES.name)}
        spec = given.get(MODEL.name)
        if spec is not None:
            if not str(spec).strip():
                raise InputError("--model: give the calibrated model's file (model.toml)")
            text = read_text(str(spec), "a model")
            if not text.strip():
                raise InputError(f"--model {spec}: an empty file, not a calibrated model")
            out |= {"model": model_label(str(spec)), "model_toml": text}
        return out

    def from_database(self, options: Mapping[str, Any], store: Store | None) -> dict[str, Any]:
        if options.get("model_toml") is not None:  # a file: the database's model of its text
            from cellcal.store.schema import model_digest

            digest = model_digest(str(options["model_toml"]))
            same = [m for m in (store.models() if store else []) if m.digest == digest]
            if not same:
                return {**options, "model_id": None}
            known = same[-1]  # that model, named as the database names it
            label = f"model {known.id} (campaign {known.campaign_id})"
            return {**options, "model": label, "model_id": known.id}
        current = None if store is None else store.current_model()
        if current is None:
            where = "the database" if store is None else store.path
            ended = [] if store is None else store.models()
            why = (
                f"model {ended[-1].id} was ended by {ended[-1].ended_by}"
                if ended
                else "no calibration is stored in it"
            )
            raise InputError(
                f"no current model in {where}: {why}; calibrate (cellcal run), or check "
                "against a model file with --model FILE"
            )
        label = f"model {current.id} (campaign {current.campaign_id})"
        return {**options, "model": label, "model_toml": current.model_toml, "model_id": current.id}

    def plan(self, config: CellConfig, options: Mapping[str, Any]) -> tuple[Plan, RobotModel]:
        from cellcal.files.models import load_model

        n = options.get("poses") or config.check.poses
        return check_plan(config, check_model(options), int(n)), load_model(
            config.robot.model
        ).model

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        return ()

    def analyse(self, done: Acquired) -> Analysis:
        with done.store.transaction():  # the check's figures and its report, or neither
            outcome = analyse_check(done)
            done.store.add_report(done.campaign_id, outcome.to_dict())
        return Analysis(outcome, None)


CHECK_KIND = CheckKind()


def analyse_check(done: Acquired) -> CheckOutcome:
    """The check's figures from its stored poses; recorded in ``checks`` (ending the
    model's validity when the robot is out of its limits)."""
    from cellcal.calib import drift
    from cellcal.calib.error_terms import Conditions
    from cellcal.campaign.pose_conditions import pose_conditions
    from cellcal.files.models import model_uncertainty
    from cellcal.store.schema import model_digest

    options = done.options
    label, text = str(options["model"]), str(options["model_toml"])
    loaded = check_model(options)
    u = model_uncertainty(text, label)
    assert loaded.T_sensor_base is not None  # check_model refuses any other
    state = drift.model_state(loaded.model, loaded.target_offset, loaded.T_sensor_base, u.pivot)
    reference = done.config.reference_sensor.name
    data = done.store.pose_data(done.campaign_id)
    seen = data.measured(reference)
    if not seen.any():
        raise CampaignError(
            f"check {done.campaign_id}: the reference sensor {reference} measured nothing"
        )
    q, m = data.q[seen], data.mean[reference][seen]
    measured_air = pose_conditions(data, seen)
    at = None if measured_air is None else Conditions(temperature_c=measured_air.temperature_c)
    errors = drift.pose_errors(state, q, m, at)
    norms = np.linalg.norm(errors, axis=1)
    model_id = options.get("model_id")
    digest = model_digest(text)
    earlier = [
        c.rms_mm
        for c in done.store.checks()
        if c.model_digest == digest and c.verdict == drift.OK and c.campaign_id != done.campaign_id
    ]
    cfg = done.config.check
    limits = drift.control_limits(
        drift.predicted_rms(state, q, u),
        u.validation_mm,
        earlier,
        cfg.warning_factor,
        cfg.recalibrate_factor,
    )
    verdict = drift.verdict(norms, limits)
    diagnosis = (
        drift.diagnose(state, q, errors, limits.sigma_mm, limits.warning_mm)
        if verdict != drift.OK
        else drift.Diagnosis(None, ())
    )
    outcome = CheckOutcome(
        done.campaign_id,
        done.store.path,
        label,
        model_id,
        digest,
        tuple(float(e) for e in norms),
        drift.rms(errors),
        float(norms.max()),
        limits,
        verdict,
        diagnosis,
        reference,
    )
    done.store.add_check(
        done.campaign_id,
        model_id,
        digest,
        rms_mm=outcome.rms_mm,
        max_mm=outcome.max_mm,
        warning_mm=limits.warning_mm,
        limit_mm=limits.limit_mm,
        verdict=verdict,
        cause=outcome.cause,
        errors_mm=outcome.errors_mm,
        ends_model=verdict == drift.RECALIBRATE,
    )
    return outcome
