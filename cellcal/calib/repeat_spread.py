"""How much a validation RMS would change if the campaign were run again.

A validation RMS after calibration is one draw: another campaign on the same cell
measures other noise, so its fit lands elsewhere within the fit's own uncertainty and
its validation poses are measured with other noise too. Five campaigns on one simulated
cell gave 0.0064–0.0181 mm; a headline without that spread claims more than it knows.

:func:`repeat_spread` draws the parameters (sensor frame and target offset included)
from the fit's a-posteriori covariance σ₀²(JᵀJ)⁻¹, propagates each draw to the
validation poses through the identification Jacobian, adds each pose's measurement
noise (its 1σ per axis) and takes the RMS of every draw: the 5th, 50th and 95th
percentiles of those RMS are the range another campaign would give, as far as the fit's
own uncertainty tells. Errors the model does not hold (temperature, compliance, a
different region) are not in it; a measured RMS above the 99.5th percentile says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.calibration_result import CalibrationResult
from cellcal.calib.error_model import jacobian
from cellcal.calib.geometry import Array

#: simulated repeats of the campaign; the percentiles are stable to about 1 % with these
DRAWS = 2000
#: the range: 90 % of the repeats
LOW_PCT, HIGH_PCT = 5.0, 95.0
#: a measured RMS above this percentile of the repeats is not chance (1 campaign in 200)
ALARM_PCT = 99.5


@dataclass(frozen=True)
class RepeatSpread:
    """The validation RMS (mm) another campaign would give: ``low``–``high`` hold 90 % of
    ``draws`` simulated repeats, ``median`` their middle, ``alarm`` is exceeded by 1 in
    200; ``measured`` is this campaign's."""

    measured: float
    low: float
    median: float
    high: float
    alarm: float
    draws: int

    @property
    def above(self) -> bool:
        """The measured RMS is above what the fit's uncertainty explains (beyond chance)."""
        return self.measured > self.alarm

    def as_dict(self) -> dict[str, object]:
        return {
            "measured_mm": self.measured,
            "low_mm": self.low,
            "median_mm": self.median,
            "high_mm": self.high,
            "alarm_mm": self.alarm,
            "percentiles": [LOW_PCT, HIGH_PCT],
            "draws": self.draws,
        }


def repeat_spread(
    result: CalibrationResult,
    q: Array,
    sigma: Array,
    measured_rms: float,
    *,
    draws: int = DRAWS,
    seed: int = 0,
) -> RepeatSpread | None:
    """The spread of the validation RMS at the poses ``q`` (rad; first target and
    session) whose measurements have the 1σ ``sigma`` (N×3, mm) per axis; None when the
    fit has no covariance (a singular normal matrix)."""
    cov = result.covariance
    if cov is None or not np.all(np.isfinite(cov)) or len(q) == 0:
        return None
    _, J = jacobian(result.state, np.asarray(q, dtype=np.float64), result.covariance_specs)
    # a square root of the covariance that tolerates rounding below zero
    values, vectors = np.linalg.eigh((cov + cov.T) / 2.0)
    root = vectors * np.sqrt(np.clip(values, 0.0, None))
    rng = np.random.default_rng(seed)
    delta = root @ rng.standard_normal((len(values), draws))  # P × draws
    errors = np.einsum("nip,pk->nik", J, delta)
    errors += np.asarray(sigma, dtype=np.float64)[:, :, None] * rng.standard_normal(errors.shape)
    rms = np.sqrt(np.mean(np.sum(errors * errors, axis=1), axis=0))
    low, median, high, alarm = np.percentile(rms, [LOW_PCT, 50.0, HIGH_PCT, ALARM_PCT])
    return RepeatSpread(
        float(measured_rms), float(low), float(median), float(high), float(alarm), draws
    )
