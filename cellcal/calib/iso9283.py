"""ISO 9283 pose accuracy (AP) and pose repeatability (RP), position part.

The test points (ISO 9283:1998, 6.2 and 7.2): in a cube of the workspace, the measuring
plane is one of the cube's diagonal planes; P1 is the cube's centre, P2…P5 lie on the
plane's diagonals, one tenth of a diagonal's length from its corners. The robot visits
P1, P2, P3, P4, P5 in turn, ``n`` cycles (30 in the standard).

For each point, from the ``n`` attained positions x_i and the commanded position c:

- AP = ‖x̄ − c‖ (and its components x̄ − c), where x̄ is the barycentre of the x_i;
- RP = l̄ + 3·S_l, where l_i = ‖x_i − x̄‖, l̄ their mean and
  S_l = √(Σ(l_i − l̄)² / (n − 1)).

Both in mm, positions in the robot base frame. Orientation accuracy (AP_a, AP_b, AP_c)
needs a sensor that measures orientation and is not computed here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.errors import InputError

#: The standard's number of cycles.
CYCLES = 30
#: P2…P5 lie this fraction of a diagonal's length from its corners.
CORNER_FRACTION = 0.1


def iso_points(centre_mm: Array, edge_mm: float) -> Array:
    """P1…P5 (5×3, mm) on the diagonal plane of a cube through its bottom corner
    (−,−,−) and top corner (+,+,+) along the x = y diagonal (in the cube's axes)."""
    c = np.asarray(centre_mm, dtype=np.float64)
    if edge_mm <= 0:
        raise InputError(f"ISO 9283 cube edge {edge_mm} mm: must be positive")
    h = edge_mm / 2.0
    corners = c + h * np.array([[-1, -1, -1], [1, 1, -1], [1, 1, 1], [-1, -1, 1]], dtype=float)
    f = CORNER_FRACTION
    # Each corner moved a tenth of its diagonal towards the opposite corner.
    p = [corners[k] + f * (corners[(k + 2) % 4] - corners[k]) for k in range(4)]
    return np.vstack([c[None], np.array(p)])


@dataclass(frozen=True)
class PointResult:
    """One test point: ``AP`` and its components (mm), ``RP``, l̄ and S_l (mm), ``n``."""

    name: str
    commanded: Array
    barycentre: Array
    ap: float
    ap_xyz: Array
    rp: float
    l_mean: float
    l_std: float
    n: int


def point_result(name: str, commanded: Array, attained: Array) -> PointResult:
    """AP and RP of one point from its ``n`` attained positions (n×3, mm)."""
    x = np.asarray(attained, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) < 2 or not np.isfinite(x).all():
        raise InputError(f"ISO 9283 point {name}: need at least 2 finite attained positions")
    bar = x.mean(axis=0)
    d = bar - np.asarray(commanded, dtype=np.float64)
    dist = np.linalg.norm(x - bar, axis=1)
    s = float(np.sqrt(np.sum((dist - dist.mean()) ** 2) / (len(dist) - 1)))
    return PointResult(
        name=name,
        commanded=np.asarray(commanded, dtype=np.float64),
        barycentre=bar,
        ap=float(np.linalg.norm(d)),
        ap_xyz=d,
        rp=float(dist.mean() + 3.0 * s),
        l_mean=float(dist.mean()),
        l_std=s,
        n=len(x),
    )


def pose_characteristics(commanded: Array, attained: Array) -> tuple[PointResult, ...]:
    """AP and RP of every point: ``commanded`` (P×3), ``attained`` (cycles×P×3), mm."""
    c = np.asarray(commanded, dtype=np.float64)
    x = np.asarray(attained, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != c.shape:
        raise InputError(f"ISO 9283: attained {x.shape} does not match commanded {c.shape}")
    return tuple(point_result(f"P{k + 1}", c[k], x[:, k]) for k in range(len(c)))
