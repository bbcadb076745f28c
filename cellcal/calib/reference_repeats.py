"""Repeated reference poses: the same joints measured again and again through a
campaign, which measure the robot's repeatability and the cell's drift directly.

For each reference pose (a label): the spread of its measured positions about their
mean (repeatability, RMS of the 3-D distances) and the straight-line trend of its
position with time (drift, mm/h, with its standard uncertainty from the line's
residuals). A drift beyond its uncertainty is what the ``drift`` error term models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array


@dataclass(frozen=True)
class ReferenceRepeat:
    """One reference pose: ``n`` measurements over ``hours``; ``repeatability_mm``: RMS
    distance from their mean; ``drift_mm_per_h``: the trend's rate (3-D length) and
    ``drift_sigma_mm_per_h`` its 1σ (NaN with fewer than 3 measurements or no time
    spread)."""

    label: str
    n: int
    hours: float
    repeatability_mm: float
    drift_mm_per_h: float
    drift_sigma_mm_per_h: float


def reference_repeats(
    labels: tuple[str, ...], positions: Array, time_s: Array
) -> tuple[ReferenceRepeat, ...]:
    """Per label (in order of first appearance): repeatability and drift of its rows
    (``positions`` N×3 mm in one frame, ``time_s`` N)."""
    out = []
    for label in dict.fromkeys(labels):
        rows = np.array([v == label for v in labels])
        p, t = positions[rows], time_s[rows] / 3600.0
        n = len(p)
        spread = math.sqrt(float(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
        rate, sigma = math.nan, math.nan
        if n >= 3 and float(np.ptp(t)) > 0:
            A = np.c_[np.ones(n), t - t.mean()]
            coef, *_ = np.linalg.lstsq(A, p, rcond=None)
            slope = coef[1]
            residual = p - A @ coef
            s2 = float(np.sum(residual**2)) / max(3 * (n - 2), 1)  # per coordinate
            var = s2 / float(np.sum((t - t.mean()) ** 2))
            rate = float(np.linalg.norm(slope))
            sigma = math.sqrt(var)
        out.append(ReferenceRepeat(label, n, float(np.ptp(t)), spread, rate, sigma))
    return tuple(out)
