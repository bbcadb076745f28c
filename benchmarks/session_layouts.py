"""Session layouts cut from a robot's calibration poses, for benchmarks/real_data.py: a
LINE (the fullest thin cylinder), a CURVE (tube around a circle), a SURFACE (slab around
a plane), each found by seeded RANSAC, and the SCATTERED rest; each with a known rigid
transform into its own sensor frame (exact for real data: coordinates only)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.calib.error_model import Index
from cellcal.calib.geometry import Array
from cellcal.calib.observations import on_a_line

#: Radii of the line's cylinder tried (mm); the fullest cylinder whose points cellcal
#: calls on a line (closer to it than 1 % of their spread along it) is the line.
LINE_MM = (1.0, 2.0, 3.0, 4.0)
#: Radius of the tube around the curve's circle, half-thickness of the surface's slab (mm).
CURVE_MM = 10.0
PLANE_MM = 10.0
#: Random pairs (line) and triples (circle, plane) tried, and how many at once.
CANDIDATES = 3000
CHUNK = 250
#: Each set-up's sensor frame in the source's: a rotation vector (deg) and a translation
#: (mm), a tracker moved around the cell. The scattered set-up stays in the source's frame,
#: the one its held-out poses were measured in.
FRAMES = {
    "line": ((0.0, 0.0, 90.0), (2500.0, -800.0, 150.0)),
    "curve": ((5.0, -3.0, 200.0), (-1800.0, 2200.0, -300.0)),
    "surface": ((-4.0, 6.0, -60.0), (900.0, 3100.0, 400.0)),
    "scattered": ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
}
LAYOUTS = tuple(FRAMES)
Mask = NDArray[np.bool_]


@dataclass(frozen=True)
class Layout:
    """A session: its ``rows`` among the calibration poses, how its target points lie
    (``how``), and ``T`` (4×4), the known rigid transform from the source's frame into
    its sensor frame."""

    name: str
    rows: Index
    how: str
    T: Array


def rigid(rotvec_deg: Sequence[float], t: Sequence[float]) -> Array:
    """The 4×4 transform of a rotation vector (deg) and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def moved(points: Array, T: Array) -> Array:
    """Points (N×3) expressed in the frame T maps them into."""
    out: Array = points @ T[:3, :3].T + T[:3, 3]
    return out


def _samples(rng: np.random.Generator, n: int, k: int) -> Index:
    """Up to CANDIDATES random k-tuples of distinct point indices."""
    idx = rng.integers(0, n, size=(CANDIDATES, k))
    out: Index = idx[np.all(np.diff(np.sort(idx, axis=1), axis=1) > 0, axis=1)]
    return out


def _to_lines(x: Array, a: Array, u: Array) -> Array:
    """Distances (k×n) of points x from k lines through a along unit u."""
    d = x[None] - a[:, None]
    along = np.einsum("knj,kj->kn", d, u)
    out: Array = np.linalg.norm(d - along[..., None] * u[:, None], axis=2)
    return out


def _to_planes(x: Array, a: Array, n: Array) -> Array:
    out: Array = np.abs(np.einsum("knj,kj->kn", x[None] - a[:, None], n))
    return out


def _to_circles(x: Array, c: Array, n: Array, r: Array) -> Array:
    """Distances of points from k circles (centre c, unit normal n, radius r)."""
    d = x[None] - c[:, None]
    h = np.einsum("knj,kj->kn", d, n)
    rho = np.linalg.norm(d - h[..., None] * n[:, None], axis=2)
    out: Array = np.hypot(h, rho - r[:, None])
    return out


def _most_inliers(
    x: Array, shapes: tuple[Array, ...], distance: Callable[..., Array], tols: Sequence[float]
) -> list[tuple[int, Mask]]:
    """For each tolerance, the candidate shape (index into ``shapes``' rows) with the
    most points within it, and those points' mask (RANSAC's count, every candidate)."""
    best: list[tuple[int, Mask]] = [(-1, np.zeros(len(x), dtype=bool)) for _ in tols]
    for s in range(0, len(shapes[0]), CHUNK):
        d = distance(x, *(p[s : s + CHUNK] for p in shapes))
        for i, tol in enumerate(tols):
            inside = d <= tol
            k = int(np.argmax(inside.sum(axis=1)))
            if inside[k].sum() > best[i][1].sum():
                best[i] = (s + k, inside[k])
    return best


def _pca(points: Array) -> tuple[Array, Array, Array]:
    """Centroid, principal directions (rows, by decreasing spread), RMS spreads."""
    c = points.mean(axis=0)
    _, sv, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt, sv / np.sqrt(len(points))


def _line(x: Array, rng: np.random.Generator) -> tuple[Mask, str]:
    ij = _samples(rng, len(x), 2)
    a, u = x[ij[:, 0]], x[ij[:, 1]] - x[ij[:, 0]]
    u /= np.linalg.norm(u, axis=1)[:, None]
    best, radius = np.zeros(len(x), dtype=bool), 0.0
    for tol, (_, mask) in zip(LINE_MM, _most_inliers(x, (a, u), _to_lines, LINE_MM), strict=True):
        c, axes, _ = _pca(x[mask])  # the inliers' own line, if it holds as many
        refit = _to_lines(x, c[None], axes[:1])[0] <= tol
        mask = refit if refit.sum() >= mask.sum() else mask
        while on_a_line(x[mask]) is None:  # cellcal's test: drop the farthest across
            c, axes, _ = _pca(x[mask])
            rows = np.flatnonzero(mask)
            mask[rows[np.argmax(_to_lines(x[rows], c[None], axes[:1])[0])]] = False
        if mask.sum() > best.sum():
            best, radius = mask, tol
    line = on_a_line(x[best])
    assert line is not None
    return best, (
        f"within {radius:g} mm of one line, {line.across_rms_mm:.2f} mm RMS across it, "
        f"{line.along_mm:.0f} mm long"
    )


def _curve(x: Array, rng: np.random.Generator) -> tuple[Mask, str]:
    t = _samples(rng, len(x), 3)
    a, u, v = x[t[:, 0]], x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]
    n = np.cross(u, v)
    nn = np.sum(n * n, axis=1)
    a, u, v, n, nn = (w[nn > 1e-9] for w in (a, u, v, n, nn))
    uu, vv = np.sum(u * u, axis=1)[:, None], np.sum(v * v, axis=1)[:, None]
    centre = a + np.cross(uu * v - vv * u, n) / (2 * nn)[:, None]  # the circumcentre
    r = np.linalg.norm(centre - a, axis=1)
    extent = float(np.ptp(x, axis=0).max())
    ok = (r >= 0.15 * extent) & (r <= 0.5 * extent)  # a curve: neither a line nor a knot
    n = n / np.sqrt(nn)[:, None]
    [(k, mask)] = _most_inliers(x, (centre[ok], n[ok], r[ok]), _to_circles, [CURVE_MM])
    c, e1 = centre[ok][k], a[ok][k] - centre[ok][k]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n[ok][k], e1)
    d = x[mask] - c
    ang = np.sort(np.degrees(np.arctan2(d @ e2, d @ e1)))
    arc = 360.0 - float(np.max(np.diff(np.append(ang, ang[0] + 360.0))))
    return mask, f"within {CURVE_MM:g} mm of a circle of radius {r[ok][k]:.0f} mm, {arc:.0f}° of it"


def _plane(x: Array, rng: np.random.Generator) -> tuple[Mask, str]:
    t = _samples(rng, len(x), 3)
    n = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-6
    [(_, mask)] = _most_inliers(x, (x[t[ok, 0]], n[ok] / norm[ok, None]), _to_planes, [PLANE_MM])
    c, axes, _ = _pca(x[mask])  # the inliers' own plane, if it holds as many
    refit = _to_planes(x, c[None], axes[2:])[0] <= PLANE_MM
    mask = refit if refit.sum() >= mask.sum() else mask
    c, axes, sv = _pca(x[mask])
    size = np.ptp((x[mask] - c) @ axes[:2].T, axis=0)
    return mask, (
        f"within {PLANE_MM:g} mm of one plane, {sv[2]:.1f} mm RMS off it, "
        f"{size[0]:.0f} × {size[1]:.0f} mm"
    )


def session_layouts(xyz: Array, seed: int = 0) -> tuple[Layout, ...]:
    """The line, the curve, the surface (each chosen among the points not taken yet)
    and the scattered rest of target points ``xyz`` (N×3, mm), with their frames."""
    rng = np.random.default_rng(seed)
    free = np.arange(len(xyz))
    out = []
    for name, find in (("line", _line), ("curve", _curve), ("surface", _plane)):
        mask, how = find(xyz[free], rng)
        out.append(Layout(name, free[mask], how, rigid(*FRAMES[name])))
        free = free[~mask]
    size = np.ptp((xyz[free] - xyz[free].mean(axis=0)) @ _pca(xyz[free])[1].T, axis=0)
    how = f"the rest, spread over {size[0]:.0f} × {size[1]:.0f} × {size[2]:.0f} mm"
    return (*out, Layout("scattered", free, how, rigid(*FRAMES["scattered"])))


def distance_change(points: Array, T: Array) -> float:
    """The largest change (mm) of a pairwise distance of ``points`` moved by T."""
    i, j = np.triu_indices(len(points), 1)
    p = moved(points, T)
    d0 = np.linalg.norm(points[i] - points[j], axis=1)
    return float(np.max(np.abs(np.linalg.norm(p[i] - p[j], axis=1) - d0)))
