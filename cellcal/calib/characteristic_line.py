"""The characteristic-line (CL) method of Liu et al. (Sensors 2018), Sec. 3.1, done right.

The paper builds two lines in each frame (A, B from pairs of common points) and makes
them coincide by three rotations, each written as a chain of seven matrices (its Eqs.
1–8): translate the rotation axis to the origin, turn it into the XOZ plane (Rx), onto
Z (Ry), rotate by θ about Z, and undo the first three. Printed errata, corrected here:

* Eq. 4 as printed is Rz(−θ); the rotation that takes A onto A′ about C = A × A′ is Rz(+θ).
* Eq. 5 as printed repeats Eq. 3; "reversing step (c)" is Ry(+β).
* θ is computed with atan2(|A × A′|, A·A′), not arccos (which loses precision near 0).
* Eq. 12 writes the translation as a sum; it is a composition: the last step moves the
  midpoint of A onto the midpoint of A′.
* Step 3 rotates about line B by the angle between A and A′ *measured about B* (their
  projections on the plane normal to B). For the paper's cube diagonals (A ⊥ B) this is
  the paper's angle; in general it keeps B on B′, which the paper's text requires.

With these fixes the result is the TRIAD attitude solution with B as the primary line
(tested against an independent TRIAD). It is exact for noise-free data but uses only
the points on its lines, so on noisy data it is less accurate than least squares — a
reproduction baseline, not the default. Degenerate: a line of coincident points, A
nearly parallel to B (the roll about them is undetermined).

Generalised form: each line may be given by more than two points; it is then the
least-squares line through them (principal direction, oriented first → last point;
its "midpoint" is their centroid).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.errors import DegenerateGeometryError, InputError

#: A and B closer than this angle (in either frame) leave the roll undetermined.
MIN_LINE_ANGLE_DEG = 1.0
#: Below this angle the result is computed but a warning is attached.
WARN_LINE_ANGLE_DEG = 10.0


@dataclass(frozen=True)
class CoincidenceStep:
    """One rotation of the chain (a row of the paper's Table 1).

    ``axis`` is (a, b, c), the rotation axis C; ``alpha``/``beta`` the angles that turn
    it onto Z; ``theta`` the rotation about it; ``point`` the point the axis passes
    through; ``T`` the 4×4 matrix of the seven-matrix chain. Angles in radians.
    """

    axis: Array
    alpha: float
    beta: float
    theta: float
    point: Array
    T: Array


@dataclass(frozen=True)
class LineFit:
    """What the CL method produced: the transform, its three steps, its warnings."""

    T: Array
    steps: tuple[CoincidenceStep, ...]
    warnings: tuple[str, ...]


def _translation(v: Array) -> Array:
    T = np.eye(4)
    T[:3, 3] = v
    return T


def _rx(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _ry(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _rz(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def chain(axis: Array, theta: float, point: Array) -> CoincidenceStep:
    """The paper's Eq. 8 (errata fixed): rotation by ``theta`` about ``axis`` through ``point``.

    T(+p) · Rx(−α) · Ry(β) · Rz(θ) · Ry(−β) · Rx(α) · T(−p), with
    cos α = c/√(b²+c²), sin α = b/√(b²+c²), cos β = √(b²+c²)/|C|, sin β = a/|C|.
    """
    a, b, c = (float(x) for x in axis)
    alpha = float(np.arctan2(b, c))
    beta = float(np.arctan2(a, np.hypot(b, c)))
    T = (
        _translation(point)
        @ _rx(-alpha)
        @ _ry(beta)
        @ _rz(theta)
        @ _ry(-beta)
        @ _rx(alpha)
        @ _translation(-point)
    )
    return CoincidenceStep(np.array([a, b, c]), alpha, beta, float(theta), point.copy(), T)


def _perpendicular(v: Array) -> Array:
    e = np.zeros(3)
    e[int(np.argmin(np.abs(v)))] = 1.0
    out: Array = np.cross(v, e)
    return out


def align_step(u: Array, v: Array, point: Array) -> CoincidenceStep:
    """Rotation about C = u × v through ``point`` that turns direction u onto direction v."""
    C = np.cross(u, v)
    s = float(np.linalg.norm(C))
    c = float(u @ v)
    theta = float(np.arctan2(s, c))
    if s <= 1e-15 * float(np.linalg.norm(u) * np.linalg.norm(v)):
        # Parallel: nothing to do. Antiparallel: any axis normal to u turns it by π.
        C = _perpendicular(u) if c < 0 else np.array([0.0, 0.0, 1.0])
        theta = np.pi if c < 0 else 0.0
    return chain(C, theta, point)


def line_through(points: Array, name: str) -> tuple[Array, Array]:
    """Direction (first → last point) and midpoint of the line through ``points`` (k×3)."""
    if len(points) == 2:
        d: Array = points[1] - points[0]
        mid: Array = 0.5 * (points[0] + points[1])
    else:
        mid = points.mean(axis=0)
        _, _, Vt = np.linalg.svd(points - mid)
        d = Vt[0] * float(np.linalg.norm(points[-1] - points[0]))
        if d @ (points[-1] - points[0]) < 0:
            d = -d
    span = float(np.max(np.linalg.norm(points - points[0], axis=1)))
    scale = max(1.0, float(np.max(np.abs(points))))
    if span <= 1e-9 * scale or float(np.linalg.norm(d)) <= 1e-9 * scale:
        raise DegenerateGeometryError(f"characteristic line {name}: its points coincide")
    return d, mid


def _angle_deg(u: Array, v: Array) -> float:
    """Angle between two lines (undirected), degrees in [0, 90]."""
    ang = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v)), abs(float(u @ v)))))
    return ang


def characteristic_line(
    src: Array,
    dst: Array,
    line_a: Sequence[int],
    line_b: Sequence[int],
) -> LineFit:
    """Fit ``T_dst_src`` by making line A, then line B, coincide (the paper's Sec. 3.1).

    ``line_a`` and ``line_b`` are indices into the rows of ``src``/``dst``, two or more
    each, in the order that defines the line's direction.
    """
    n = len(src)
    for name, idx in (("A", line_a), ("B", line_b)):
        if len(idx) < 2:
            raise InputError(f"characteristic line {name} needs at least 2 points, got {len(idx)}")
        if len(set(idx)) != len(idx):
            raise InputError(f"characteristic line {name} uses a point twice")
        if any(i < 0 or i >= n for i in idx):
            raise InputError(f"characteristic line {name}: point index out of range 0..{n - 1}")
    ia, ib = list(line_a), list(line_b)
    A, mA = line_through(src[ia], "A")
    B, _ = line_through(src[ib], "B")
    A2, mA2 = line_through(dst[ia], "A")
    B2, _ = line_through(dst[ib], "B")

    warnings: list[str] = []
    for frame, u, v in (("source", A, B), ("destination", A2, B2)):
        ang = _angle_deg(u, v)
        if ang < MIN_LINE_ANGLE_DEG:
            raise DegenerateGeometryError(
                f"characteristic lines A and B are {ang:.3g}° apart in the {frame} frame "
                f"(need at least {MIN_LINE_ANGLE_DEG}°): the roll about them is undetermined"
            )
        if ang < WARN_LINE_ANGLE_DEG:
            warnings.append(
                f"characteristic lines A and B are only {ang:.3g}° apart in the {frame} frame; "
                "the rotation about them is poorly determined"
            )

    # Step 1: turn A onto A′ about C1 = A × A′ through the midpoint of A.
    s1 = align_step(A, A2, mA)
    # Step 2: turn B (as moved by step 1) onto B′ about C2 = B × B′ through the moved midpoint of B.
    T = s1.T
    B_1 = T[:3, :3] @ B
    pts_b = src[ib] @ T[:3, :3].T + T[:3, 3]
    s2 = align_step(B_1, B2, pts_b.mean(axis=0))
    T = s2.T @ T
    # Step 3: rotate about line B (now parallel to B′) until A lies in the plane of A′ and B′.
    A_2 = T[:3, :3] @ A
    b = B2 / np.linalg.norm(B2)
    pa = A_2 - (A_2 @ b) * b
    pb = A2 - (A2 @ b) * b
    theta3 = float(np.arctan2(np.cross(pa, pb) @ b, pa @ pb))
    pts_b = src[ib] @ T[:3, :3].T + T[:3, 3]
    s3 = chain(b, theta3, pts_b.mean(axis=0))
    T = s3.T @ T
    # Translation: the midpoint of A onto the midpoint of A′.
    T = _translation(mA2 - (T[:3, :3] @ mA + T[:3, 3])) @ T
    return LineFit(T=T, steps=(s1, s2, s3), warnings=tuple(warnings))


def auto_lines(src: Array) -> tuple[list[int], list[int]]:
    """Pick two long, well-separated lines when none are given.

    A joins the two points farthest apart; B is the pair that maximises its length times
    the sine of its angle to A (the cube's diagonals for a cube). O(n²); fine for the few
    hundred points a cell measures.
    """
    D = src[:, None, :] - src[None, :, :]
    L = np.linalg.norm(D, axis=2)
    i, j = np.unravel_index(int(np.argmax(L)), L.shape)
    a = D[j, i] / L[i, j]
    perp = np.linalg.norm(np.cross(D, a), axis=2)
    k, m = np.unravel_index(int(np.argmax(perp)), perp.shape)
    ia, ib = sorted((int(i), int(j))), sorted((int(k), int(m)))
    return ia, ib
