"""Every point shown: per-point residuals with a robust outlier flag.

A point is flagged when its error length stands out from the others by the modified
z-score of Iglewicz and Hoaglin, z = 0.6745 (d − median) / MAD, above 3.5 — a median
and a median absolute deviation, so that the outlier cannot hide itself by inflating
the spread it is measured against. One point "dominates" a fit when it alone carries
more than half of the sum of squared errors; a robust fit is then worth trying.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array

#: Modified z-score above which a point is flagged (Iglewicz & Hoaglin 1993).
OUTLIER_Z = 3.5
#: Share of the sum of squared errors above which one point dominates a fit.
DOMINANT_SHARE = 0.5


@dataclass(frozen=True)
class PointResidual:
    """One point's residual (measured − fitted, mm) and its flag."""

    name: str
    dx: float
    dy: float
    dz: float
    error: float
    z: float
    outlier: bool

    def as_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "dx_mm": self.dx,
            "dy_mm": self.dy,
            "dz_mm": self.dz,
            "error_mm": self.error,
            "z": self.z,
            "outlier": self.outlier,
        }


def robust_z(d: Array) -> Array:
    """Modified z-scores of the values ``d`` (0 where the MAD is 0)."""
    d = np.asarray(d, dtype=np.float64)
    med = float(np.median(d))
    mad = float(np.median(np.abs(d - med)))
    if mad <= 1e-12 * max(abs(med), 1e-300):
        out: Array = np.zeros_like(d)
        return out
    z: Array = 0.6745 * (d - med) / mad
    return z


def point_residuals(
    names: Sequence[str], residuals: Array, scores: Array | None = None
) -> tuple[PointResidual, ...]:
    """Per-point rows; ``scores`` (default: the error lengths) are what the outlier flag
    is computed on — e.g. leave-one-out errors, which an outlier cannot pull down."""
    r = np.asarray(residuals, dtype=np.float64)
    d = np.linalg.norm(r, axis=1)
    s = d if scores is None else np.asarray(scores, dtype=np.float64)
    z = robust_z(np.where(np.isfinite(s), s, d))
    enough = len(d) >= 5
    return tuple(
        PointResidual(
            str(n),
            float(v[0]),
            float(v[1]),
            float(v[2]),
            float(e),
            float(s),
            bool(enough and s > OUTLIER_Z),
        )
        for n, v, e, s in zip(names, r, d, z, strict=True)
    )


def dominant(points: Sequence[PointResidual]) -> PointResidual | None:
    """The point carrying more than half of the sum of squared errors, if any."""
    if len(points) < 4:
        return None
    sq = np.array([p.error**2 for p in points])
    total = float(sq.sum())
    k = int(np.argmax(sq))
    return points[k] if total > 0 and sq[k] > DOMINANT_SHARE * total else None
