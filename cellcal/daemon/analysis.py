"""After acquisition: register each sensor to the robot base, calibrate the robot from
the reference sensor, and validate on the validation poses inside and outside the
cube. Reads the store, writes its results back, returns a summary."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcal.calib.acceptance import ACCURACY_CLASS_MM, CHECK_REGISTRATION, check_data
from cellcal.calib.error_model import predict
from cellcal.calib.geometry import Array
from cellcal.calib.identification import CalibrationResult, calibrate, fit_frames
from cellcal.calib.outliers import PointResidual, point_residuals
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.validation import ErrorStats
from cellcal.daemon.plan import CALIBRATION, VALIDATION
from cellcal.daemon.store import PoseData, Store
from cellcal.errors import AcceptanceError, CampaignError
from cellcal.modelfiles import builtin_models, calibrated_toml

#: Liu et al. 2018, Sec. 4.2 and Table 3 (mm): error after calibration with another
#: registration method, with the characteristic-line method, and outside the region.
PAPER = {"other_method_mm": 0.436, "cl_inside_mm": 0.200, "cl_outside_mm": 0.323}
#: Floor of a per-axis σ of a pose mean (mm), so that one quiet pose cannot dominate.
SIGMA_FLOOR_MM = 1e-4


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
                "sigma0": c.sigma0,
                "identified": list(c.identified),
                "unidentifiable": list(c.unidentifiable),
                "warnings": list(c.warnings),
            },
            "points": [p.as_dict() for p in self.points],
            "outliers": [p.name for p in self.points if p.outlier],
            "paper": PAPER,
        }


def mean_sigma(data: PoseData, sensor: str) -> Array:
    """The 1σ (mm, per axis) of each pose's mean position: the samples' standard
    deviation over √n, floored — the weights of the analysis (and of the report's CSVs)."""
    s = data.std[sensor] / np.sqrt(np.maximum(data.n[sensor], 1))[:, None]
    out: Array = np.maximum(s, SIGMA_FLOOR_MM)
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
) -> CampaignSummary:
    """Register, calibrate, validate; store the results; return the summary. A result
    that fails an acceptance check raises :class:`AcceptanceError` and stores nothing of
    the analysis (the samples stay), unless ``accept``."""
    data = store.pose_data(campaign_id)
    role = np.array(data.role)
    region = np.array(data.region)
    cal = role == CALIBRATION
    val = role == VALIDATION
    if reference not in data.mean:
        raise CampaignError(
            f"campaign {campaign_id}: no samples from the reference sensor {reference!r}"
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
    )
    registrations = []
    writes: list[tuple[str, tuple[Any, ...]]] = []
    for sensor in sorted(data.mean):
        m = data.mean[sensor][cal]
        s = sigma(sensor, cal)
        check = check_data(nominal, q_cal, m, nominal.tool)
        if check and not accept:
            raise AcceptanceError(check[0].check, f"sensor {sensor}: {check[0].message}")
        base = fit_frames(nominal, q_cal, m, s)
        e_nom = m - predict(base, q_cal)
        if _rms(e_nom) > ACCURACY_CLASS_MM and not accept:
            raise AcceptanceError(
                CHECK_REGISTRATION,
                f"sensor {sensor}: the nominal model with best-fit frames leaves RMS "
                f"{_rms(e_nom):.3g} mm, far worse than any robot's accuracy class: its samples "
                "do not belong to this robot's poses (another target, a clock out of step)",
            )
        after = fit_frames(result.calibrated, q_cal, m, s)
        e_cal = m - predict(after, q_cal)
        T = base.T_sensor_base
        registrations.append(
            SensorRegistration(
                sensor=sensor,
                n=int(cal.sum()),
                T_sensor_base=T,
                target_offset_mm=base.tool,
                rms_nominal_mm=_rms(e_nom),
                max_nominal_mm=float(np.max(np.linalg.norm(e_nom, axis=1))),
                rms_calibrated_mm=_rms(e_cal),
                T_sensor_base_calibrated=after.T_sensor_base,
                target_offset_calibrated_mm=after.tool,
            )
        )
        n_cal = int(cal.sum())
        e_max_nom = float(np.max(np.linalg.norm(e_nom, axis=1)))
        e_max_cal = float(np.max(np.linalg.norm(e_cal, axis=1)))
        writes.append((sensor, ("nominal", n_cal, _rms(e_nom), e_max_nom, T, base.tool)))
        writes.append(
            (
                sensor,
                ("calibrated", n_cal, _rms(e_cal), e_max_cal, after.T_sensor_base, after.tool),
            )
        )

    baseline = fit_frames(nominal, q_cal, ref_m[cal], sigma(reference, cal))
    e_before = ref_m[val] - predict(baseline, data.q[val])
    e_after = ref_m[val] - result.predict(data.q[val])
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
    summary = CampaignSummary(
        campaign_id=campaign_id,
        reference=reference,
        n_calibration=int(cal.sum()),
        n_validation=int(val.sum()),
        registrations=tuple(registrations),
        calibration=result,
        validation_before=ErrorStats.of(e_before),
        validation_after=ErrorStats.of(e_after),
        inside=inside,
        outside=outside,
        regions=regions,
        points=point_residuals([str(int(i)) for i in data.idx[cal]], result.residuals),
    )
    # All results of one analysis in one transaction: a crash leaves none or all.
    with store.transaction():
        for sensor, args in writes:
            store.add_registration(campaign_id, sensor, *args)
        store.add_calibration(
            campaign_id,
            reference,
            n_points=result.n_points,
            rms_before_mm=result.rms_before,
            rms_after_mm=result.rms_after,
            condition_number=result.condition_number,
            identified=result.identified,
            unidentifiable=result.unidentifiable,
            model_toml=calibrated_toml(result, None, f"campaign {campaign_id}", summary.points),
        )
        store.add_report(campaign_id, summary.to_dict())
    return summary
