"""A ChArUco board's chessboard corners to a few hundredths of a pixel, from the
straight edges that meet at each corner.

OpenCV's ``CharucoDetector`` interpolates each corner from the markers around it and
refines it with ``cornerSubPix``, whose window takes in the neighbouring markers'
borders: on blurred, distorted or oblique views its corners are off by 0.05–1.5 px, and
by the most where the board is seen most obliquely. Here each corner is measured from
the four square edges that meet there, as :mod:`cellcal.calib.marker_corners` measures a
marker's:

* the board's pose in the view (from a first calibration: intrinsics and ``solvePnP``)
  says where each edge between a black and a white square runs in the image;
* each such edge is measured on every pixel row (or column, whichever crosses it more
  squarely) between 20 % and 80 % of its length: over a window across the edge the grey
  levels' sum splits between the black square's level and the white margin's exactly
  where the edge is (pixels integrate area, lens blur is symmetric). The window reaches
  into the black square and into the white margin around the marker of the white
  square, never beyond, whatever the view's obliquity (the board's own geometry bounds
  it, mapped into the image by the pose);
* the two edges on each side of a corner lie on one straight line of the board, which
  the lens bends into a smooth curve: a parabola is fitted to the points of both (in
  pixels, along the curve's chord), and the corner is where the two curves through it
  meet. Nothing here depends on the intrinsics being right: they only place the
  windows, which three passes then centre on the edge.

A corner is left out, alone, when a line through it cannot be measured: an edge cut by
the image's border, hidden, too faint, or whose white margin is too narrow in the image
for its level to be read (a board seen very obliquely across that direction). Measured
on rendered views (blur 0.8 px, noise 2 grey levels, barrel distortion, up to 65°):
see docs/photogrammetry.md.

Pure numerics: an image, the board, a camera model and the board's pose in; corner ids
and pixels out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.camera_rig import Board
from cellcal.calib.geometry import Array

Image = NDArray[Any]

#: Fraction of each edge measured (its ends are bent by the neighbouring edges).
EDGE_SPAN = (0.2, 0.8)
#: How far a blurred edge reaches, px: windows and level probes stay this far from any
#: other edge of the board.
BLUR_REACH_PX = 1.6
#: Largest reach of the window into either side, px: beyond about 3.5 σ of the blur the
#: edge's tail is below a ten-thousandth of a pixel, and a longer window adds only noise.
WINDOW_MAX_PX = 3.0
#: Where the black square's level is read: this far into it, px (up to its middle).
DARK_PROBE_PX = 5.0
#: Passes over each edge, each centring the window on the last estimate.
PASSES = 3
#: Least difference between the white and the black level.
MIN_CONTRAST = 20.0
#: Fewest points on a line through a corner (its two edges together).
MIN_LINE_POINTS = 8
#: A corner whose lines fit worse than this many times the view's median is left out.
GATE = 1.5
#: Residual beyond which an edge point is dropped from its line, in robust σ.
REJECT_SIGMA = 3.0


@dataclass(frozen=True, eq=False)
class RefinedCorners:
    """Corners measured from edges: ids (n,) and pixels (n, 2), the ids that could not be
    measured, and each kept corner's line-fit RMS (px, the larger of its two lines)."""

    ids: NDArray[np.int64]
    pixels: Array
    unmeasured: NDArray[np.int64]
    line_rms_px: Array


@dataclass(frozen=True)
class _Segment:
    """One square edge: from ``a`` to ``b`` (board mm), with the black square on the side
    ``dark`` (a unit vector, board coordinates) and the white one opposite."""

    a: Array
    b: Array
    dark: Array


def _white_squares(board: Board) -> NDArray[np.bool_]:
    """(ny, nx): which squares hold a marker (white squares)."""
    nx, ny = board.squares
    white = np.zeros((ny, nx), dtype=bool)
    for c in board.cv_board().getObjPoints():
        centre = np.asarray(c, dtype=np.float64)[:, :2].mean(axis=0)
        white[int(centre[1] // board.square), int(centre[0] // board.square)] = True
    return white


def _segments(board: Board) -> dict[tuple[int, int, int], _Segment]:
    """Every square edge between a black and a white square, keyed (axis, i, j): axis 0
    runs along x from grid point (i, j) to (i+1, j), axis 1 along y to (i, j+1)."""
    nx, ny = board.squares
    s = board.square
    white = _white_squares(board)
    out = {}
    for j in range(1, ny):  # horizontal lines y = j·s, squares above (j−1) and below (j)
        for i in range(nx):
            if white[j - 1, i] != white[j, i]:
                dark = np.array([0.0, 1.0 if white[j - 1, i] else -1.0])
                out[(0, i, j)] = _Segment(
                    np.array([i * s, j * s]), np.array([(i + 1) * s, j * s]), dark
                )
    for i in range(1, nx):  # vertical lines x = i·s, squares left (i−1) and right (i)
        for j in range(ny):
            if white[j, i - 1] != white[j, i]:
                dark = np.array([1.0 if white[j, i - 1] else -1.0, 0.0])
                out[(1, i, j)] = _Segment(
                    np.array([i * s, j * s]), np.array([i * s, (j + 1) * s]), dark
                )
    return out


class BoardEdges:
    """Measures a board's corners from its edges (one instance per board)."""

    def __init__(self, board: Board) -> None:
        self.board = board
        self.margin = 0.5 * (board.square - board.marker)
        self.segments = _segments(board)
        self.nx, self.ny = board.squares

    def refine(
        self,
        grey: Image,
        K: Array,
        dist: Array,
        rvec: Array,
        tvec: Array,
        ids: NDArray[np.int64],
    ) -> RefinedCorners:
        """The corners ``ids`` measured in ``grey`` (float or 8-bit grey levels), the board
        posed at (rvec, tvec) in a camera (K, dist)."""
        img = np.asarray(grey, dtype=np.float32)
        project = _Projector(K, dist, rvec, tvec)
        cache: dict[tuple[int, int, int], Array | None] = {}

        def points(key: tuple[int, int, int]) -> Array | None:
            if key not in cache:
                seg = self.segments.get(key)
                cache[key] = None if seg is None else self._edge(img, project, seg)
            return cache[key]

        kept, pixels, rms, lost = [], [], [], []
        for k in np.asarray(ids, dtype=np.int64).ravel():
            i, j = int(k) % (self.nx - 1) + 1, int(k) // (self.nx - 1) + 1
            h = [p for p in (points((0, i - 1, j)), points((0, i, j))) if p is not None]
            v = [p for p in (points((1, i, j - 1)), points((1, i, j))) if p is not None]
            guess = project(np.array([[i * self.board.square, j * self.board.square]]))[0]
            corner = _meet(h, v, guess)
            if corner is None:
                lost.append(int(k))
                continue
            kept.append(int(k))
            pixels.append(corner[0])
            rms.append(corner[1])
        line_rms = np.array(rms, dtype=np.float64)
        if len(kept) >= 4:  # a line measured much worse than the others: a bad edge
            bad = line_rms > GATE * float(np.median(line_rms))
            lost += [k for k, b in zip(kept, bad, strict=True) if b]
            kept = [k for k, b in zip(kept, bad, strict=True) if not b]
            pixels = [p for p, b in zip(pixels, bad, strict=True) if not b]
            line_rms = line_rms[~bad]
        return RefinedCorners(
            np.array(kept, dtype=np.int64),
            np.array(pixels, dtype=np.float64).reshape(-1, 2),
            np.array(sorted(lost), dtype=np.int64),
            line_rms,
        )

    def _edge(self, img: Image, project: _Projector, seg: _Segment) -> Array | None:
        """Sub-pixel points (n, 2) where the edge ``seg`` crosses pixel rows (or columns);
        None when it cannot be measured."""
        h, w = img.shape
        t = np.linspace(0.0, 1.0, 33)
        along_mm = seg.a[None, :] + t[:, None] * (seg.b - seg.a)[None, :]
        curve = project(along_mm)
        d = curve[-1] - curve[0]
        ax = 1 if abs(d[0]) < abs(d[1]) else 0  # 1: scan rows (edge runs down the image)
        scan, across = curve[:, ax], curve[:, 1 - ax]
        lo_t, hi_t = np.interp(EDGE_SPAN, t, scan)
        js = np.arange(np.ceil(min(lo_t, hi_t)), np.floor(max(lo_t, hi_t)) + 1)
        if len(js) < 3 or not np.all(np.diff(scan) * np.sign(scan[-1] - scan[0]) > 0):
            return None
        order = np.argsort(scan)
        e = np.interp(js, scan[order], across[order])
        tj = np.interp(js, scan[order], t[order])
        q = seg.a[None, :] + tj[:, None] * (seg.b - seg.a)[None, :]
        # board mm per pixel along the scan line, at each point (the pose's local map)
        J = project.jacobian(q)  # (n, 2, 2): d pixel / d board
        step_px = np.zeros((len(js), 2))
        step_px[:, 1 - ax] = 1.0
        try:
            u = np.linalg.solve(J, step_px[..., None])[..., 0]  # board mm per px
        except np.linalg.LinAlgError:
            return None
        normal = seg.dark  # across the edge, toward the black square
        rate = u @ normal  # mm across per px along the scan (signed)
        if np.any(np.abs(rate) < 1e-9):
            return None
        sign = np.sign(rate)  # +1: the black square lies toward larger scan coordinate
        dark_px = 0.5 * self.board.square / np.abs(rate)
        bright_px = self.margin / np.abs(rate)
        if np.median(bright_px) < 2.0 * BLUR_REACH_PX + 0.2:
            return None  # the white margin is too narrow in the image to read its level
        reach_dark = np.minimum(dark_px - BLUR_REACH_PX, WINDOW_MAX_PX)
        reach_bright = np.minimum(bright_px - BLUR_REACH_PX, WINDOW_MAX_PX)
        # the levels are read from three pixels a row where there is room (one in a
        # narrow margin): their noise would otherwise shift a whole edge
        probe_dark = np.minimum(0.5 * dark_px, DARK_PROBE_PX)[:, None] + np.array([-1, 0, 1])
        spread = np.where(bright_px >= 2.0 * BLUR_REACH_PX + 2.0, 1.0, 0.0)
        probe_bright = (0.5 * bright_px)[:, None] + spread[:, None] * np.array([-1, 0, 1])
        j_int = js.astype(np.int64)
        ok = np.ones(len(js), dtype=bool)
        offs = np.arange(-int(WINDOW_MAX_PX) - 2, int(WINDOW_MAX_PX) + 3)

        def gather(i: Array) -> Array:
            i = np.asarray(i, dtype=np.int64)
            jj = np.broadcast_to(j_int.reshape((-1,) + (1,) * (i.ndim - 1)), i.shape)
            if ax == 1:
                inside = (i >= 0) & (i < w) & (jj >= 0) & (jj < h)
                vals = img[np.clip(jj, 0, h - 1), np.clip(i, 0, w - 1)]
            else:
                inside = (i >= 0) & (i < h) & (jj >= 0) & (jj < w)
                vals = img[np.clip(i, 0, h - 1), np.clip(jj, 0, w - 1)]
            return np.where(inside, vals.astype(np.float64), np.nan)

        dark = bright = float("nan")
        for _ in range(PASSES):
            dark_v = gather(np.rint((e + sign * probe_dark.T).T))
            bright_v = gather(np.rint((e - sign * probe_bright.T).T))
            dark = _level(np.where(ok[:, None], dark_v, np.nan))
            bright = _level(np.where(ok[:, None], bright_v, np.nan))
            if not np.isfinite(dark) or not np.isfinite(bright) or bright - dark < MIN_CONTRAST:
                return None
            # the window [lo, hi] along the scan: toward the black square by reach_dark,
            # toward the white margin by reach_bright
            lo = np.where(sign > 0, e - reach_bright, e - reach_dark)
            hi = np.where(sign > 0, e + reach_dark, e + reach_bright)
            left = np.where(sign > 0, bright, dark)
            right = np.where(sign > 0, dark, bright)
            pix = np.rint(e).astype(np.int64)[:, None] + offs[None, :]
            inside = np.minimum(pix + 0.5, hi[:, None]) - np.maximum(pix - 0.5, lo[:, None])
            weight = np.clip(inside, 0.0, 1.0)
            vals = gather(pix)
            total = np.where(weight > 0, vals * weight, 0.0).sum(axis=1)
            valid = np.isfinite(np.where(weight > 0, vals, 0.0)).all(axis=1)
            with np.errstate(all="ignore"):
                e_new = (total + left * lo - right * hi) / (left - right)
            step_ok = (
                valid
                & np.isfinite(e_new)
                & (np.abs(e_new - e) < np.minimum(reach_dark, reach_bright) + 1.0)
            )
            ok &= step_ok
            e = np.where(step_ok, e_new, e)
        ok &= (reach_dark >= 1.0) & (reach_bright >= 0.6)
        if ok.sum() < 3:
            return None
        pts = np.empty((int(ok.sum()), 2))
        pts[:, ax] = js[ok]
        pts[:, 1 - ax] = e[ok]
        return pts


def _level(values: Array) -> float:
    """The mean of grey levels within 3 robust σ of their median (NaN when none)."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return float("nan")
    med = float(np.median(v))
    mad = 1.4826 * float(np.median(np.abs(v - med)))
    return float(v[np.abs(v - med) <= max(3.0 * mad, 1.0)].mean())


class _Projector:
    """Board points (mm, z = 0) to pixels through the camera model, and the local map."""

    def __init__(self, K: Array, dist: Array, rvec: Array, tvec: Array) -> None:
        self.K, self.dist = np.asarray(K, float), np.asarray(dist, float)
        self.rvec, self.tvec = np.asarray(rvec, float), np.asarray(tvec, float)

    def __call__(self, xy: Array) -> Array:
        p = np.column_stack([xy, np.zeros(len(xy))])
        px, _ = cv2.projectPoints(p, self.rvec, self.tvec, self.K, self.dist)
        out: Array = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return out

    def jacobian(self, xy: Array, delta: float = 0.5) -> Array:
        n = len(xy)
        dx, dy = np.array([delta, 0.0]), np.array([0.0, delta])
        stacked = np.concatenate([xy + dx, xy - dx, xy + dy, xy - dy])
        p = self(stacked).reshape(4, n, 2)
        J = np.empty((n, 2, 2))
        J[:, :, 0] = (p[0] - p[1]) / (2 * delta)
        J[:, :, 1] = (p[2] - p[3]) / (2 * delta)
        return J


def _curve(parts: list[Array]) -> tuple[Array, Array, Array, Array, float] | None:
    """A parabola fitted to a line's points: (origin, direction, normal, coefficients of
    the offset along the normal as a quadratic in the distance along the direction, RMS).
    Points beyond ``REJECT_SIGMA`` robust σ are dropped (two passes)."""
    if not parts:
        return None
    pts = np.concatenate(parts)
    if len(pts) < MIN_LINE_POINTS:
        return None
    origin = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - origin, full_matrices=False)
    direction, normal = vt[0], vt[1]
    s = (pts - origin) @ direction
    n = (pts - origin) @ normal
    keep = np.ones(len(pts), dtype=bool)
    degree = 2 if len(parts) == 2 else 1
    coef = np.zeros(3)
    for _ in range(3):
        A = np.vander(s[keep], degree + 1)
        c, *_ = np.linalg.lstsq(A, n[keep], rcond=None)
        coef = np.concatenate([np.zeros(3 - len(c)), c])
        r = n - np.polyval(coef, s)
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.abs(r) <= max(REJECT_SIGMA * mad, 1e-6)
        if new.sum() < MIN_LINE_POINTS or np.array_equal(new, keep):
            break
        keep = new
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    return origin, direction, normal, coef, rms


def _meet(h: list[Array], v: list[Array], guess: Array) -> tuple[Array, float] | None:
    """Where the curves fitted to the two lines through a corner meet (px), and the larger
    of their RMS; None when either line cannot be fitted or they do not meet near the
    expected corner."""
    ch, cv_ = _curve(h), _curve(v)
    if ch is None or cv_ is None:
        return None
    p = np.asarray(guess, dtype=np.float64).copy()
    for _ in range(8):
        F, Jf = [], []
        for origin, direction, normal, coef, _ in (ch, cv_):
            s = float((p - origin) @ direction)
            n = float((p - origin) @ normal)
            slope = 2 * coef[0] * s + coef[1]
            F.append(n - float(np.polyval(coef, s)))
            Jf.append(normal - slope * direction)
        try:
            dp = np.linalg.solve(np.array(Jf), -np.array(F))
        except np.linalg.LinAlgError:
            return None
        p += dp
        if np.linalg.norm(dp) < 1e-9:
            break
    if not np.all(np.isfinite(p)) or np.linalg.norm(p - guess) > 3.0:
        return None
    return p, max(ch[4], cv_[4])
