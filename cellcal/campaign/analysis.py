"""After acquisition: register each sensor to the robot base, calibrate the robot from
the reference sensor, validate on the validation poses inside and outside the cube, and
fuse what the sensors measured of each pose (``calib/fusion.py``). Reads the store,
writes its results back, returns a summary.

Each pose mean is weighted by its uncertainty: the covariance of the mean when the
sensor gave one (the rig: its diagonal in the sensor's frame, whose z is about the
cameras' depth; the fit takes per-axis weights), else the samples' standard deviation
over √n. A pose a sensor did not measure (a broken beam, a target the cameras did not
see) is left out of that sensor's registration; a pose without the reference sensor is
left out of the calibration and the validation, and the summary says how many."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcal import __version__
from cellcal.calib.acceptance import ACCURACY_CLASS_MM, CHECK_REGISTRATION, check_data
from cellcal.calib.error_model import predict
from cellcal.calib.error_terms import Conditions
from cellcal.calib.fusion import Estimate, carried, fuse, in_base
from cellcal.calib.geometry import Array
from cellcal.calib.identification import CalibrationResult, calibrate, fit_frames
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.outliers import PointResidual, point_residuals
from cellcal.calib.reference_repeats import ReferenceRepeat
from cellcal.calib.repeat_spread import RepeatSpread, repeat_spread
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.validation import ErrorStats, Validation
from cellcal.campaign.plan import CALIBRATION, VALIDATION
from cellcal.campaign.pose_conditions import pose_conditions, repeats_of, with_pose_payloads
from cellcal.errors import AcceptanceError, CampaignError
from cellcal.files.models import builtin_models, calibrated_toml
from cellcal.store.database import PoseData, Store
from cellcal.store.results import (
    AnalysisResults,
    CalibrationRow,
    FusedRow,
    RegistrationRow,
)

#: Liu et al. 2018, Sec. 4.2 and Table 3 (mm): error after calibration with another
#: registration method, with the characteristic-line method, and outside the region.
PAPER = {"other_method_mm": 0.436, "cl_inside_mm": 0.200, "cl_outside_mm": 0.323}
#: Floor of a per-axis σ of a pose mean (mm), so that one quiet pose cannot dominate.
SIGMA_FLOOR_MM = 1e-4
#: How a campaign's model file says its validation was held out.
VALIDATION_IN_CUBE = "the campaign's validation poses in the cube"
#: A sensor that measured fewer calibration poses than this is not registered.
MIN_REGISTRATION_POSES = 6


@dataclass(frozen=True)
class SensorRegistration:
    """A sensor registered to the robot base: ``T_sensor_base``, its target offset, and the
    RMS/max residual with the nominal geometry and with the calibrated one (mm)."""

    sensor: str
    n: int
    T_sensor_base: Array
    target_offset_mm: Array
    rms_nominal_mm: float
    max_nominal_mm: float
    rms_calibrated_mm: float
    T_sensor_base_calibrated: Array
    target_offset_calibrated_mm: Array


@dataclass(frozen=True)
class Agreement:
    """How one sensor agrees with the reference after registration, over the ``n`` poses
    both measured: the RMS distance of its estimate of the reference point from the
    reference's (mm) and the fused χ² per degree of freedom (about 1 when both
    covariances tell the truth)."""

    sensor: str
    n: int
    rms_mm: float
    chi2_per_dof: float


@dataclass(frozen=True)
class RegionErrors:
    region: str
    before: ErrorStats
    after: ErrorStats


@dataclass(frozen=True)
class CampaignSummary:
    campaign_id: int
    reference: str
    n_calibration: int
    n_validation: int
    registrations: tuple[SensorRegistration, ...]
    calibration: CalibrationResult
    validation_before: ErrorStats
    validation_after: ErrorStats
    inside: RegionErrors | None
    outside: RegionErrors | None
    regions: tuple[RegionErrors, ...]
    #: the reference sensor's residual at each calibration pose (named by plan index)
    points: tuple[PointResidual, ...] = ()
    agreements: tuple[Agreement, ...] = ()
    #: poses fused (at least one sensor measured them)
    n_fused: int = 0
    warnings: tuple[str, ...] = ()
    #: the validation RMS after calibration another campaign would give (None: no
    #: covariance)
    spread: RepeatSpread | None = None
    #: the repeated reference poses' repeatability and drift (none planned: empty)
    repeats: tuple[ReferenceRepeat, ...] = ()

    @property
    def improvement_pct(self) -> float:
        return 100.0 * (1.0 - self.validation_after.rms / self.validation_before.rms)

    def to_dict(self) -> dict[str, Any]:
        def stats(s: ErrorStats) -> dict[str, float]:
            return {"n": s.n, "mean_mm": s.mean, "rms_mm": s.rms, "max_mm": s.max, "p95_mm": s.p95}

        def region(r: RegionErrors | None) -> dict[str, Any] | None:
            return (
                None
                if r is None
                else {"region": r.region, "before": stats(r.before), "after": stats(r.after)}
            )

        c = self.calibration
        return {
            "campaign_id": self.campaign_id,
            "reference_sensor": self.reference,
            "n_calibration_poses": self.n_calibration,
            "n_validation_poses": self.n_validation,
            "rms_before_mm": self.validation_before.rms,
            "rms_after_mm": self.validation_after.rms,
            "improvement_pct": self.improvement_pct,
            "rms_after_spread": None if self.spread is None else self.spread.as_dict(),
            "reference_poses": [
                {
                    "pose": r.label,
                    "n": r.n,
                    "hours": r.hours,
                    "repeatability_mm": r.repeatability_mm,
                    "drift_mm_per_h": r.drift_mm_per_h,
                    "drift_sigma_mm_per_h": r.drift_sigma_mm_per_h,
                }
                for r in self.repeats
            ],
            "cellcal_version": __version__,
            "validation_before": stats(self.validation_before),
            "validation_after": stats(self.validation_after),
            "inside": region(self.inside),
            "outside": region(self.outside),
            "regions": [region(r) for r in self.regions],
            "registrations": [
                {
                    "sensor": r.sensor,
                    "n": r.n,
                    "rms_nominal_mm": r.rms_nominal_mm,
                    "max_nominal_mm": r.max_nominal_mm,
                    "rms_calibrated_mm": r.rms_calibrated_mm,
                    "T_sensor_base": r.T_sensor_base.tolist(),
                    "target_offset_mm": r.target_offset_mm.tolist(),
                    "T_sensor_base_calibrated": r.T_sensor_base_calibrated.tolist(),
                    "target_offset_calibrated_mm": r.target_offset_calibrated_mm.tolist(),
                }
                for r in self.registrations
            ],
            "calibration": {
                "sensor": self.reference,
                "fit_rms_before_mm": c.rms_before,
                "fit_rms_after_mm": c.rms_after,
                "condition_number": c.condition_number,
                "condition_number_equal_weights": c.condition_number_equal_weights,
                "sigma0": c.sigma0,
                "identified": list(c.identified),
                "unidentifiable": list(c.unidentifiable),
                "warnings": list(c.warnings),
            },
            "agreements": [
                {"sensor": a.sensor, "n": a.n, "rms_mm": a.rms_mm, "chi2_per_dof": a.chi2_per_dof}
                for a in self.agreements
            ],
            "n_fused": self.n_fused,
            "warnings": list(self.warnings),
            "points": [p.as_dict() for p in self.points],
            "outliers": [p.name for p in self.points if p.outlier],
            "paper": PAPER,
        }


def mean_sigma(data: PoseData, sensor: str) -> Array:
    """The 1σ (mm, per axis) of each pose's mean position: from the mean's covariance
    where the sensor gave one, else the samples' standard deviation over √n; floored —
    the weights of the analysis (and of the report's CSVs)."""
    s = data.std[sensor] / np.sqrt(np.maximum(data.n[sensor], 1))[:, None]
    own = np.sqrt(np.abs(np.diagonal(data.cov[sensor], axis1=1, axis2=2)))
    out: Array = np.maximum(np.where(np.isfinite(own), own, s), SIGMA_FLOOR_MM)
    return out


def mean_covariance(data: PoseData, sensor: str) -> Array:
    """The covariance (N×3×3, mm²) of each pose's mean: the sensor's own where it gave
    one, else diagonal from :func:`mean_sigma`."""
    own = data.cov[sensor]
    diag = np.einsum("ni,ij->nij", mean_sigma(data, sensor) ** 2, np.eye(3))
    out: Array = np.where(np.asarray(np.isfinite(own).all(axis=(1, 2)))[:, None, None], own, diag)
    return out


def _rms(e: Array) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(e) else float("nan")


def analyse(
    store: Store,
    campaign_id: int,
    nominal: RobotModel,
    reference: str,
    *,
    accept: bool = False,
    terms: str = "geometric",
    payload_of: Mapping[int, float | None] | None = None,
) -> CampaignSummary:
    """Register, calibrate, validate; store the results (all in one transaction: none or
    all of them); return the summary. A result that fails an acceptance check raises
    :class:`AcceptanceError` and stores nothing of the analysis (the samples stay), unless
    ``accept``; ``terms``: the error terms beyond geometry the calibration may add;
    ``payload_of``: each pose's planned payload by its index."""
    data = with_pose_payloads(store.pose_data(campaign_id), payload_of)
    summary, results = analysis_of(
        data, campaign_id, nominal, reference, accept=accept, terms=terms
    )
    store.save_analysis(results)
    return summary


def analysis_of(
    data: PoseData,
    campaign_id: int,
    nominal: RobotModel,
    reference: str,
    *,
    accept: bool = False,
    terms: str = "geometric",
) -> tuple[CampaignSummary, AnalysisResults]:
    """The analysis of a campaign's stored poses (a function of ``data`` alone): its
    summary, and the rows the store keeps of it."""
    role = np.array(data.role)
    region = np.array(data.region)
    if reference not in data.mean:
        raise CampaignError(
            f"campaign {campaign_id}: no samples from the reference sensor {reference!r}"
        )
    has_ref = data.measured(reference)
    cal = (role == CALIBRATION) & has_ref
    val = (role == VALIDATION) & has_ref
    warnings = []
    lost = len(has_ref) - int(np.count_nonzero(has_ref))
    if lost:
        warnings.append(
            f"{lost} pose(s) without the reference sensor {reference!r} (broken beam): "
            "left out of the calibration and the validation"
        )
    q_cal = data.q[cal]

    def sigma(sensor: str, mask: Array) -> Array:
        out: Array = mean_sigma(data, sensor)[mask]
        return out

    ref_m = data.mean[reference]
    if not val.any():
        raise CampaignError(f"campaign {campaign_id}: no validation poses were measured")
    alternatives = builtin_models()
    result = calibrate(
        nominal,
        q_cal,
        ref_m[cal],
        sigma(reference, cal),
        accept=accept,
        alternatives=alternatives,
        terms=terms,
        conditions=pose_conditions(data, cal),
    )
    registrations = []
    writes: list[RegistrationRow] = []
    for sensor in sorted(data.mean):
        mask = (role == CALIBRATION) & data.measured(sensor)
        if int(mask.sum()) < MIN_REGISTRATION_POSES:
            warnings.append(
                f"sensor {sensor}: measured {int(mask.sum())} calibration poses, fewer than "
                f"{MIN_REGISTRATION_POSES}: not registered"
            )
            continue
        reg, rows = _register(
            nominal,
            result,
            data.q[mask],
            data.mean[sensor][mask],
            sigma(sensor, mask),
            sensor,
            accept,
            pose_conditions(data, mask),
        )
        registrations.append(reg)
        writes += rows

    baseline = fit_frames(nominal, q_cal, ref_m[cal], sigma(reference, cal))
    e_before = ref_m[val] - predict(baseline, data.q[val])
    e_after = ref_m[val] - result.predict(data.q[val], None, pose_conditions(data, val))
    reg_val = region[val]

    def errors(mask: Array, name: str) -> RegionErrors | None:
        if not mask.any():
            return None
        return RegionErrors(name, ErrorStats.of(e_before[mask]), ErrorStats.of(e_after[mask]))

    inside = errors(reg_val == "cube", "cube")
    outside = errors(reg_val != "cube", "outside")
    regions = tuple(
        r for r in (errors(reg_val == name, name) for name in sorted(set(reg_val))) if r is not None
    )
    estimates = sensor_estimates(
        data,
        result.calibrated,
        [
            (r.sensor, r.T_sensor_base_calibrated, r.target_offset_calibrated_mm)
            for r in registrations
        ],
        reference,
    )
    fused = [fuse(list(e.values())) if e else None for e in estimates]
    after = ErrorStats.of(e_after)
    spread = repeat_spread(result, data.q[val], sigma(reference, val), after.rms)
    if spread is not None and spread.above:
        warnings.append(
            f"the validation RMS after calibration, {after.rms:.4f} mm, is above what the "
            f"fit's own uncertainty explains (199 of 200 repeats below {spread.alarm:.4f} "
            "mm): an error the model does not hold (temperature, compliance, a loose "
            "target) or validation poses unlike the calibration's"
        )
    summary = CampaignSummary(
        campaign_id=campaign_id,
        reference=reference,
        n_calibration=int(cal.sum()),
        n_validation=int(val.sum()),
        registrations=tuple(registrations),
        calibration=result,
        validation_before=ErrorStats.of(e_before),
        validation_after=after,
        inside=inside,
        outside=outside,
        regions=regions,
        points=point_residuals([str(int(i)) for i in data.idx[cal]], result.residuals),
        agreements=_agreements(estimates, reference),
        n_fused=sum(f is not None for f in fused),
        warnings=tuple(warnings),
        spread=spread,
        repeats=repeats_of(data, reference),
    )
    calibration = CalibrationRow(
        sensor=reference,
        n_points=result.n_points,
        rms_before_mm=result.rms_before,
        rms_after_mm=result.rms_after,
        condition_number=result.condition_number,
        identified=tuple(result.identified),
        unidentifiable=tuple(result.unidentifiable),
        model_toml=calibrated_toml(
            result,
            _held_out(e_before, e_after, reg_val == "cube"),
            f"campaign {campaign_id}",
            summary.points,
        ),
    )
    fused_rows = tuple(
        FusedRow(int(pose_id), f.sensors, f.xyz, f.cov, f.chi2)
        for pose_id, f in zip(data.pose_id, fused, strict=True)
        if f is not None
    )
    results = AnalysisResults(
        campaign_id, tuple(writes), calibration, fused_rows, summary.to_dict()
    )
    return summary, results


def _held_out(e_before: Array, e_after: Array, inside: Array) -> Validation | None:
    """The validation in the cube as the model file keeps it (a check's limits start from
    it: ``calib/drift.py``); None without a validation pose there."""
    if not inside.any():
        return None
    b, a = e_before[inside], e_after[inside]
    return Validation(VALIDATION_IN_CUBE, ErrorStats.of(b), ErrorStats.of(a), b, a)


def _register(
    nominal: RobotModel,
    result: CalibrationResult,
    q: Array,
    m: Array,
    s: Array,
    sensor: str,
    accept: bool,
    conditions: Conditions | None = None,
) -> tuple[SensorRegistration, list[RegistrationRow]]:
    """One sensor registered with the nominal and with the calibrated geometry; refused
    when its samples do not follow the robot. Returns the registration and its rows."""
    check = check_data(nominal, q, m, nominal.target_offset)
    if check and not accept:
        raise AcceptanceError(check[0].check, f"sensor {sensor}: {check[0].message}")
    base = fit_frames(nominal, q, m, s)
    e_nom = m - predict(base, q)
    if _rms(e_nom) > ACCURACY_CLASS_MM and not accept:
        raise AcceptanceError(
            CHECK_REGISTRATION,
            f"sensor {sensor}: the nominal model with best-fit frames leaves RMS "
            f"{_rms(e_nom):.3g} mm, far worse than any robot's accuracy class: its samples "
            "do not belong to this robot's poses (another target, a clock out of step)",
        )
    after = fit_frames(result.calibrated, q, m, s, None, conditions)
    e_cal = m - predict(after, q, None, conditions)
    e_max_nom = float(np.max(np.linalg.norm(e_nom, axis=1)))
    e_max_cal = float(np.max(np.linalg.norm(e_cal, axis=1)))
    reg = SensorRegistration(
        sensor=sensor,
        n=len(q),
        T_sensor_base=base.T_sensor_base,
        target_offset_mm=base.target_offset,
        rms_nominal_mm=_rms(e_nom),
        max_nominal_mm=e_max_nom,
        rms_calibrated_mm=_rms(e_cal),
        T_sensor_base_calibrated=after.T_sensor_base,
        target_offset_calibrated_mm=after.target_offset,
    )
    rows = [
        RegistrationRow(
            sensor,
            "nominal",
            len(q),
            _rms(e_nom),
            e_max_nom,
            base.T_sensor_base,
            base.target_offset,
        ),
        RegistrationRow(
            sensor,
            "calibrated",
            len(q),
            _rms(e_cal),
            e_max_cal,
            after.T_sensor_base,
            after.target_offset,
        ),
    ]
    return reg, rows


def sensor_estimates(
    data: PoseData,
    calibrated: RobotModel,
    frames: Sequence[tuple[str, Array, Array]],
    reference: str,
) -> list[dict[str, Estimate]]:
    """At each pose, each registered sensor's estimate of the reference point (base frame
    of the calibrated model), from the poses it measured; ``frames``: per sensor its
    name, ``T_sensor_base`` and target offset with the calibrated geometry."""
    ref_offset = next(offset for sensor, _, offset in frames if sensor == reference)
    R = target_kinematics(calibrated, data.q, np.zeros(3), jacobian=False).R_flange
    out: list[dict[str, Estimate]] = [{} for _ in data.idx]
    for sensor, T_sensor_base, offset in frames:
        cov = mean_covariance(data, sensor)
        for k in np.flatnonzero(data.measured(sensor)):
            e = in_base(sensor, data.mean[sensor][k], cov[k], T_sensor_base)
            out[k][sensor] = carried(e, R[k], offset, ref_offset)
    return out


def _agreements(estimates: list[dict[str, Estimate]], reference: str) -> tuple[Agreement, ...]:
    """Each other sensor against the reference, over the poses both measured."""
    pairs: dict[str, list[tuple[float, float]]] = {}
    for at_pose in estimates:
        ref = at_pose.get(reference)
        for sensor, e in at_pose.items():
            if ref is not None and sensor != reference:
                d2 = float(np.sum((e.xyz - ref.xyz) ** 2))
                pairs.setdefault(sensor, []).append((d2, fuse([ref, e]).chi2 or 0.0))
    return tuple(
        Agreement(
            sensor,
            len(v),
            float(np.sqrt(np.mean([d2 for d2, _ in v]))),
            float(np.mean([c for _, c in v])) / 3.0,
        )
        for sensor, v in sorted(pairs.items())
    )
