"""What a campaign's report shows, computed from the database and the stored calibrated
model (read-only): each sensor's registration residual at every calibration pose (with
the nominal and the calibrated geometry), the reference sensor's error at every
validation pose before and after calibration, the parameters with their σ, the
identification Jacobian's singular values, the per-pose fit residuals, each sensor
against the reference, and, when asked, the registration methods compared.

Everything is recomputed with the analysis' own functions from what it stored, so the
report's figures are the analysis' numbers (the test checks that they equal the stored
summary); nothing here writes to the database.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cellcal.calib.error_model import State, jacobian, parameter_specs, predict
from cellcal.calib.geometry import Array, apply
from cellcal.calib.identification import fit_frames
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.registration import fit_rigid
from cellcal.calib.robot_model import RobotModel, model_from_dict
from cellcal.calib.term_effect import TermEffect, term_effects
from cellcal.campaign.analysis import mean_sigma, sensor_estimates
from cellcal.campaign.payloads import pose_payloads
from cellcal.campaign.plan import CALIBRATION, VALIDATION
from cellcal.campaign.pose_conditions import pose_conditions
from cellcal.errors import CellcalError
from cellcal.files.models import load_model
from cellcal.store.air import AirRange
from cellcal.store.database import PoseData, Store
from cellcal.store.validity import CheckRow, ModelRow

#: Registration methods the comparison runs (the paper's Table 4, with the line method).
METHODS = ("svd", "quaternion", "rodrigues", "small-angle", "three-point", "line")


@dataclass(frozen=True)
class SensorResiduals:
    """One sensor's residual (measured − predicted, mm, its own frame) at each
    calibration pose it measured, with the nominal and the calibrated geometry."""

    sensor: str
    idx: Array
    nominal: Array
    calibrated: Array


@dataclass(frozen=True)
class PoseAgreement:
    """A sensor's estimate of the reference point against the reference's, per pose."""

    sensor: str
    idx: Array
    distance_mm: Array


@dataclass(frozen=True)
class ValidationPoses:
    """The reference sensor's error (mm, N×3) at each validation pose, before (nominal
    model, best-fit frames) and after calibration; where they are (base frame, mm)."""

    idx: Array
    region: tuple[str, ...]
    position: Array
    before: Array
    after: Array


@dataclass(frozen=True)
class MethodComparison:
    """Registering the reference sensor by one method (the calibrated geometry's
    predictions at the calibration poses against the measurements), and the error it
    leaves at the validation poses (mm)."""

    method: str
    fit_rms_mm: float
    validation_rms_mm: float
    validation_max_mm: float
    error: str = ""


@dataclass(frozen=True)
class DriftHistory:
    """The model a report is about (the one a calibration made, or the one a check
    compared with; None: a file none of the database's) and every check of it so far,
    oldest first (a check's report: up to itself)."""

    model: ModelRow | None
    checks: tuple[CheckRow, ...]


@dataclass(frozen=True)
class ReportData:
    campaign_id: int
    facts: dict[str, Any]
    summary: dict[str, Any] | None
    model: dict[str, Any] | None  # the calibrated-model document (TOML), if any
    calibration_positions: Array  # base frame (mm), calibration poses the fit used
    residuals: tuple[SensorResiduals, ...]
    agreements: tuple[PoseAgreement, ...]
    validation: ValidationPoses | None
    singular_values: Array
    methods: tuple[MethodComparison, ...]
    events: tuple[tuple[str, str, int | None, str], ...]
    retries: dict[str, int]
    #: the air the sensors that report it measured in (an emScon tracker's meteo)
    air: tuple[AirRange, ...] = ()
    #: the model's checks (a calibration's, a check's; None for an ISO 9283 test)
    drift: DriftHistory | None = None
    #: how far each of the model's error terms moves the target at the calibration poses
    term_effects: tuple[TermEffect, ...] = ()


def _state(doc: dict[str, Any]) -> State:
    keys = ("name", "convention", "joint", "term", "payload_com_mm")
    model = model_from_dict({k: doc[k] for k in keys if k in doc}, "stored model")
    T = np.array(doc["sensor"]["matrix"], dtype=np.float64)
    return State(
        model, np.array(doc["tool"]["xyz"], dtype=np.float64), T[:3, :3], T[:3, 3], np.zeros(3)
    )


def _frame_state(model: RobotModel, reg: dict[str, Any], calibrated: bool) -> State:
    key = "_calibrated" if calibrated else ""
    T = np.array(reg[f"T_sensor_base{key}"], dtype=np.float64)
    target_offset = np.array(reg[f"target_offset{key}_mm"], dtype=np.float64)
    return State(model, target_offset, T[:3, :3], T[:3, 3], np.zeros(3))


def _singular_values(
    state: State, q: Array, measured: Array, sigma: Array, identified: list[str]
) -> Array:
    """Singular values of the identification Jacobian of the identified parameters,
    weighted by 1/σ and unit-scaled per column as the identification does, largest
    first (their ratio is the condition number)."""
    specs = parameter_specs(state.model)
    # The sensor frame's six parameters are always estimated (and not listed).
    keep = [
        k for k, s in enumerate(specs) if s.name in set(identified) or s.kind.startswith("frame")
    ]
    if not keep or len(q) == 0:
        return np.zeros(0)
    # Frame rotations turn about the measurements' centroid, as in the identification.
    about = State(state.model, state.target_offsets, state.Rs, state.ts, measured.mean(axis=0))
    _, J = jacobian(about, q, specs)
    A = (J / sigma[:, :, None]).reshape(-1, len(specs))[:, keep]
    norms = np.linalg.norm(A, axis=0)
    out: Array = np.asarray(
        np.linalg.svd(A / np.where(norms > 0, norms, 1.0), compute_uv=False), dtype=np.float64
    )
    return out


def _compare_methods(
    state: State, q_cal: Array, m_cal: Array, q_val: Array, m_val: Array
) -> tuple[MethodComparison, ...]:
    """Each registration method's fit of the reference sensor's frame and the validation
    error it leaves, with the calibrated geometry and target offset held."""
    base_cal = target_kinematics(state.model, q_cal, state.target_offset, jacobian=False).p
    base_val = target_kinematics(state.model, q_val, state.target_offset, jacobian=False).p
    out = []
    for method in METHODS:
        try:
            fit = fit_rigid(base_cal, m_cal, method=method)
        except CellcalError as exc:
            out.append(MethodComparison(method, float("nan"), float("nan"), float("nan"), str(exc)))
            continue
        e = np.linalg.norm(m_val - apply(fit.T, base_val), axis=1)
        out.append(MethodComparison(method, fit.rms, float(np.sqrt(np.mean(e**2))), float(e.max())))
    return tuple(out)


def _registration_residuals(
    data: PoseData, nominal: RobotModel, calibrated: RobotModel, regs: list[dict[str, Any]]
) -> tuple[SensorResiduals, ...]:
    role = np.array(data.role)
    out = []
    for reg in regs:
        sensor = reg["sensor"]
        mask = (role == CALIBRATION) & data.measured(sensor)
        q, m = data.q[mask], data.mean[sensor][mask]
        e_nom = m - predict(_frame_state(nominal, reg, False), q)
        at = pose_conditions(data, mask)
        e_cal = m - predict(_frame_state(calibrated, reg, True), q, None, at)
        out.append(SensorResiduals(sensor, data.idx[mask], e_nom, e_cal))
    return tuple(out)


def drift_history(store: Store, campaign_id: int, summary: dict[str, Any] | None) -> DriftHistory:
    """The model campaign ``campaign_id`` made (a calibration) or checked (a check), and
    its checks so far: by the model's digest, so a model given as a file has its own."""
    if summary is not None and summary.get("kind") == "check":
        model_id, digest = summary.get("model_id"), str(summary.get("model_digest"))
        model = store.model(int(model_id)) if isinstance(model_id, int) else None
        checks = [c for c in store.checks() if c.model_digest == digest]
        checks = [c for c in checks if c.campaign_id <= campaign_id]
        return DriftHistory(model, tuple(checks))
    model = store.model_of_campaign(campaign_id)
    if model is None:
        return DriftHistory(None, ())
    return DriftHistory(model, tuple(c for c in store.checks() if c.model_digest == model.digest))


def with_planned_payloads(store: Store, campaign_id: int, data: PoseData) -> PoseData:
    """The poses' payloads, as the campaign's stored configuration planned them."""
    row = store.campaign(campaign_id)
    try:
        planned = json.loads(row.config_json).get("campaign", {}).get("payloads_kg") or []
    except (ValueError, AttributeError):
        return data
    kg = pose_payloads([float(v) for v in planned], row.n_poses, data.idx)
    return data if kg is None else replace(data, payload_kg=kg)


def report_data(
    store: Store, campaign_id: int, facts: dict[str, Any], *, methods: bool = False
) -> ReportData:
    """Everything the report shows of campaign ``campaign_id``."""
    data = with_planned_payloads(store, campaign_id, store.pose_data(campaign_id))
    summary = store.latest_report(campaign_id)
    model_toml = store.latest_model_toml(campaign_id)
    events = store.event_rows(campaign_id)
    retries = store.retries_by_sensor(campaign_id)
    air = store.air_ranges(campaign_id)
    drift = None if facts.get("iso9283") else drift_history(store, campaign_id, summary)
    empty = np.zeros((0, 3))
    if summary is None or model_toml is None:
        return ReportData(
            campaign_id,
            facts,
            summary,
            None,
            empty,
            (),
            (),
            None,
            np.zeros(0),
            (),
            events,
            retries,
            air,
            drift,
        )
    doc = tomllib.loads(model_toml)
    state = _state(doc)
    nominal = load_model(str(facts["model"])).model
    reference = str(summary["reference_sensor"])
    role = np.array(data.role)
    has_ref = data.measured(reference)
    cal = (role == CALIBRATION) & has_ref
    val = (role == VALIDATION) & has_ref
    ref = data.mean[reference]
    baseline = fit_frames(nominal, data.q[cal], ref[cal], mean_sigma(data, reference)[cal])
    validation = ValidationPoses(
        idx=data.idx[val],
        region=tuple(np.array(data.region)[val]),
        position=target_kinematics(state.model, data.q[val], state.target_offset, jacobian=False).p,
        before=ref[val] - predict(baseline, data.q[val]),
        after=ref[val] - predict(state, data.q[val], None, pose_conditions(data, val)),
    )
    regs = list(summary["registrations"])
    agreements = []
    frames = [
        (
            str(r["sensor"]),
            np.array(r["T_sensor_base_calibrated"], dtype=np.float64),
            np.array(r["target_offset_calibrated_mm"], dtype=np.float64),
        )
        for r in regs
    ]
    estimates = sensor_estimates(data, state.model, frames, reference)
    for reg in regs:
        sensor = reg["sensor"]
        pairs = [
            (int(data.idx[k]), float(np.linalg.norm(e[sensor].xyz - e[reference].xyz)))
            for k, e in enumerate(estimates)
            if sensor != reference and sensor in e and reference in e
        ]
        if pairs:
            agreements.append(
                PoseAgreement(
                    sensor, np.array([i for i, _ in pairs]), np.array([d for _, d in pairs])
                )
            )
    return ReportData(
        campaign_id=campaign_id,
        facts=facts,
        summary=summary,
        model=json.loads(json.dumps(doc, default=str)),
        calibration_positions=target_kinematics(
            state.model, data.q[cal], state.target_offset, jacobian=False
        ).p,
        residuals=_registration_residuals(data, nominal, state.model, regs),
        agreements=tuple(agreements),
        validation=validation,
        singular_values=_singular_values(
            state,
            data.q[cal],
            ref[cal],
            mean_sigma(data, reference)[cal],
            list(doc["fit"]["identified"]),
        ),
        methods=_compare_methods(state, data.q[cal], ref[cal], data.q[val], ref[val])
        if methods
        else (),
        events=events,
        retries=retries,
        air=air,
        drift=drift,
        term_effects=term_effects(
            state.model, state.target_offset, data.q[cal], pose_conditions(data, cal)
        ),
    )
