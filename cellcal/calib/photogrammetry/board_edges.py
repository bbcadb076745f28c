"""A ChArUco board's chessboard corners to a few hundredths of a pixel, from the
straight edges that meet at each corner.

OpenCV's ``CharucoDetector`` interpolates each corner from the markers around it and
refines it with ``cornerSubPix``, whose window takes in the neighbouring markers'
borders: on blurred, distorted or oblique views its corners are off by 0.05–1.5 px, and
by the most where the board is seen most obliquely. Here each corner is measured from
the four square edges that meet there, as :mod:`cellcal.calib.photogrammetry.marker_corners`
measures a
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

All the edges a view's corners need are measured together, in arrays padded to the
longest edge's rows, and all the lines through them fitted together.

Pure numerics: an image, the board, a camera model and the board's pose in; corner ids
and pixels out.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.camera_rig import Board
from cellcal.calib.photogrammetry.marker_corners import row_median

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
#: Most edges × rows measured in one batch: an edge the pose stretches across far more
#: rows than the image has is measured apart, not padded into every other edge's rows.
BATCH_ROWS = 1 << 18


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
        img = np.asarray(grey)
        if img.dtype not in (np.uint8, np.float32):
            img = img.astype(np.float32)
        project = _Projector(K, dist, rvec, tvec)
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if len(ids) == 0:
            none = np.zeros(0, dtype=np.int64)
            return RefinedCorners(none, np.zeros((0, 2)), none, np.zeros(0))
        i, j = ids % (self.nx - 1) + 1, ids // (self.nx - 1) + 1
        # each corner's two lines (horizontal, then vertical), each of two edges
        line_edges = [
            key
            for a, b in zip(i.tolist(), j.tolist(), strict=True)
            for key in ((0, a - 1, b), (0, a, b), (1, a, b - 1), (1, a, b))
        ]
        keys = list(dict.fromkeys(k for k in line_edges if k in self.segments))
        pts, ok = self._edges(img, project, [self.segments[k] for k in keys])
        # an edge the board does not have is the empty one appended last (index -1)
        pts = np.concatenate([pts, np.zeros((1, *pts.shape[1:]))])
        ok = np.concatenate([ok, np.zeros((1, ok.shape[1]), dtype=bool)])
        where = {k: n for n, k in enumerate(keys)}
        slots = np.array([where.get(k, -1) for k in line_edges], dtype=np.int64).reshape(-1, 2)
        measured = np.asarray(ok[slots].any(axis=2))  # (lines, 2): which edges were measured
        curves = _curves(
            pts[slots].reshape(len(slots), -1, 2),
            ok[slots].reshape(len(slots), -1),
            np.asarray(measured.all(axis=1)),
        )
        board_xy = np.column_stack([i, j]).astype(np.float64) * self.board.square
        corners, met, line_rms = _meet(curves, project(board_xy))
        kept, lost = ids[met].tolist(), ids[~met].tolist()
        pixels, line_rms = corners[met], line_rms[met]
        if len(kept) >= 4:  # a line measured much worse than the others: a bad edge
            bad = line_rms > GATE * float(np.median(line_rms))
            lost += [k for k, b in zip(kept, bad, strict=True) if b]
            kept = [k for k, b in zip(kept, bad, strict=True) if not b]
            pixels, line_rms = pixels[~bad], line_rms[~bad]
        return RefinedCorners(
            np.array(kept, dtype=np.int64),
            pixels.reshape(-1, 2),
            np.array(sorted(lost), dtype=np.int64),
            line_rms,
        )

    def _edges(
        self, img: Image, project: _Projector, segs: list[_Segment]
    ) -> tuple[Array, NDArray[np.bool_]]:
        """Sub-pixel points (E, R, 2) where each edge of ``segs`` crosses pixel rows (or
        columns), padded to the most rows R, and which of them were measured (E, R): none
        of an edge that cannot be measured."""
        n_e = len(segs)
        if n_e == 0:
            return np.zeros((0, 1, 2)), np.zeros((0, 1), dtype=bool)
        a = np.array([s.a for s in segs])
        b = np.array([s.b for s in segs])
        t = np.linspace(0.0, 1.0, 33)
        along_mm = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
        curve = project(along_mm.reshape(-1, 2)).reshape(n_e, len(t), 2)
        d = curve[:, -1] - curve[:, 0]
        by_rows = (np.abs(d[:, 0]) < np.abs(d[:, 1]))[:, None]  # the edge runs down the image
        scan = np.where(by_rows, curve[..., 1], curve[..., 0])
        across = np.where(by_rows, curve[..., 0], curve[..., 1])
        # the rows (or columns) between EDGE_SPAN of the edge: np.interp's arithmetic
        k = np.searchsorted(t, EDGE_SPAN, side="right") - 1
        slope = (scan[:, k + 1] - scan[:, k]) / (t[k + 1] - t[k])
        ends = slope * (np.array(EDGE_SPAN) - t[k]) + scan[:, k]
        with np.errstate(invalid="ignore"):
            first, last = np.ceil(ends.min(axis=1)), np.floor(ends.max(axis=1))
            count = np.where(np.isfinite(first + last), last - first + 1, 0).astype(np.int64)
            rising = np.sign(scan[:, -1] - scan[:, 0])
            monotone = np.all(np.diff(scan, axis=1) * rising[:, None] > 0, axis=1)
        alive = (count >= 3) & monotone
        n_r = int(count[alive].max(initial=0))
        if n_r == 0:
            return np.zeros((n_e, 1, 2)), np.zeros((n_e, 1), dtype=bool)
        if n_e > 1 and n_e * n_r > BATCH_ROWS:
            return self._halves(img, project, segs, count)
        ok = alive[:, None] & (np.arange(n_r) < count[:, None])
        js = np.where(ok, first[:, None] + np.arange(n_r), 0.0)
        # where the pose puts the edge on each row, and the board point there: np.interp
        # on the curve ordered along the scan
        up = (rising > 0)[:, None]
        xs = np.where(up, scan, scan[:, ::-1])
        at = np.clip((xs[:, None, :] <= js[..., None]).sum(axis=2) - 1, 0, len(t) - 2)

        def interp(ys: Array) -> Array:
            rise = np.take_along_axis(np.diff(ys, axis=1) / np.diff(xs, axis=1), at, axis=1)
            out: Array = rise * (js - np.take_along_axis(xs, at, axis=1))
            return out + np.take_along_axis(ys, at, axis=1)

        with np.errstate(all="ignore"):
            e = np.where(ok, interp(np.where(up, across, across[:, ::-1])), 0.0)
            tj = interp(np.where(up, t, t[::-1]))
        q = a[:, None, :] + tj[..., None] * (b - a)[:, None, :]
        # board mm across the edge (toward the black square) per px along the scan line,
        # at each point (the pose's local map)
        edge_of = np.broadcast_to(np.arange(n_e)[:, None], ok.shape)[ok]
        step_px = np.zeros((len(edge_of), 2))
        step_px[:, 0], step_px[:, 1] = by_rows[edge_of, 0], ~by_rows[edge_of, 0]
        u = _per_px(project.jacobian(q[ok]), step_px, edge_of)  # board mm per px
        rate = np.ones(ok.shape)
        rate[ok] = (u * np.array([s.dark for s in segs])[edge_of]).sum(axis=1)
        # an edge the view turns edge-on on any row (or whose map there cannot be
        # inverted) is not measured
        alive &= ~np.any(ok & ~(np.abs(rate) >= 1e-9), axis=1)
        ok &= alive[:, None]
        return self._measure(img, by_rows, js, e, np.where(ok, rate, 1.0), ok)

    def _halves(
        self, img: Image, project: _Projector, segs: list[_Segment], count: NDArray[np.int64]
    ) -> tuple[Array, NDArray[np.bool_]]:
        """:meth:`_edges` of the shorter half of ``segs`` (``count`` rows each) and of the
        longer half apart, put together."""
        order = np.argsort(count, kind="stable")
        parts = [order[: len(order) // 2], order[len(order) // 2 :]]
        done = [self._edges(img, project, [segs[k] for k in part]) for part in parts]
        n_r = max(p.shape[1] for p, _ in done)
        pts, ok = np.zeros((len(segs), n_r, 2)), np.zeros((len(segs), n_r), dtype=bool)
        for part, (p, m) in zip(parts, done, strict=True):
            pts[part, : p.shape[1]], ok[part, : m.shape[1]] = p, m
        return pts, ok

    def _measure(
        self,
        img: Image,
        by_rows: NDArray[np.bool_],
        js: Array,
        e: Array,
        rate: Array,
        ok: NDArray[np.bool_],
    ) -> tuple[Array, NDArray[np.bool_]]:
        """The edges measured on their rows: ``js`` (E, R) the scan coordinate of each
        row, ``e`` where the pose puts the edge across it, ``rate`` the board mm across
        the edge (toward the black square) per px along the scan, ``ok`` the rows to
        measure; as :meth:`_edges`."""
        n_e = len(js)
        h, w = img.shape
        sign = np.sign(rate)  # +1: the black square lies toward larger scan coordinate
        dark_px = 0.5 * self.board.square / np.abs(rate)
        bright_px = self.margin / np.abs(rate)
        # the white margin too narrow in the image to read its level
        ok &= ~(row_median(np.where(ok, bright_px, np.nan)) < 2.0 * BLUR_REACH_PX + 0.2)[:, None]
        reach_dark = np.minimum(dark_px - BLUR_REACH_PX, WINDOW_MAX_PX)
        reach_bright = np.minimum(bright_px - BLUR_REACH_PX, WINDOW_MAX_PX)
        # the levels are read from three pixels a row where there is room (one in a
        # narrow margin): their noise would otherwise shift a whole edge
        three = np.array([-1.0, 0.0, 1.0])
        probe_dark = np.minimum(0.5 * dark_px, DARK_PROBE_PX)[..., None] + three
        spread = np.where(bright_px >= 2.0 * BLUR_REACH_PX + 2.0, 1.0, 0.0)
        probe_bright = (0.5 * bright_px)[..., None] + spread[..., None] * three
        offs = np.arange(-int(WINDOW_MAX_PX) - 2, int(WINDOW_MAX_PX) + 3)
        # the pixel at scan coordinate j, across coordinate i: row j, column i when the
        # scan lines are rows; row i, column j when they are columns
        flat = img.reshape(-1)
        j = js.astype(np.int64)[..., None]
        rows = by_rows[..., None]
        j_at = np.where(rows, np.clip(j, 0, h - 1) * w, np.clip(j, 0, w - 1))
        j_in = (j >= 0) & (j < np.where(rows, h, w))
        i_step: Image = np.where(rows, 1, w)
        i_end: Image = np.where(rows, w, np.int64(h))

        def gather(i: Image) -> Array:
            """Grey levels at across coordinates ``i`` (E, R, k) on each edge's rows; NaN
            outside the image."""
            i = i.astype(np.int64)
            vals = flat.take(j_at + np.clip(i, 0, i_end - 1) * i_step).astype(np.float64)
            out: Array = np.where(j_in & (i >= 0) & (i < i_end), vals, np.nan)
            return out

        for _ in range(PASSES):
            dark_v = gather(np.rint(e[..., None] + sign[..., None] * probe_dark))
            bright_v = gather(np.rint(e[..., None] - sign[..., None] * probe_bright))
            dark = _levels(np.where(ok[..., None], dark_v, np.nan).reshape(n_e, -1))
            bright = _levels(np.where(ok[..., None], bright_v, np.nan).reshape(n_e, -1))
            read = np.isfinite(dark) & np.isfinite(bright) & ~(bright - dark < MIN_CONTRAST)
            ok &= read[:, None]
            # the window [lo, hi] along the scan: toward the black square by reach_dark,
            # toward the white margin by reach_bright
            lo = np.where(sign > 0, e - reach_bright, e - reach_dark)
            hi = np.where(sign > 0, e + reach_dark, e + reach_bright)
            left = np.where(sign > 0, bright[:, None], dark[:, None])
            right = np.where(sign > 0, dark[:, None], bright[:, None])
            pix = np.rint(e).astype(np.int64)[..., None] + offs
            inside = np.minimum(pix + 0.5, hi[..., None]) - np.maximum(pix - 0.5, lo[..., None])
            weight = np.clip(inside, 0.0, 1.0)
            vals = gather(pix)
            total = np.where(weight > 0, vals * weight, 0.0).sum(axis=2)
            valid = np.isfinite(np.where(weight > 0, vals, 0.0)).all(axis=2)
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
        ok &= (ok.sum(axis=1) >= 3)[:, None]
        pts = np.stack([np.where(by_rows, e, js), np.where(by_rows, js, e)], axis=2)
        return pts, ok


def _per_px(J: Array, step_px: Array, edge_of: NDArray[np.int64]) -> Array:
    """``J⁻¹ step_px`` for each row (n, 2); NaN on every row of an edge whose local map
    cannot be inverted."""
    with contextlib.suppress(np.linalg.LinAlgError):
        return np.asarray(np.linalg.solve(J, step_px[..., None])[..., 0], dtype=np.float64)
    out = np.full(step_px.shape, np.nan)
    for k in np.unique(edge_of):
        sel = edge_of == k
        with contextlib.suppress(np.linalg.LinAlgError):
            out[sel] = np.linalg.solve(J[sel], step_px[sel][..., None])[..., 0]
    return out


def _levels(values: Array) -> Array:
    """Per row of ``values`` (m, k): the mean of its grey levels within 3 robust σ of
    their median, NaN ignored (NaN for a row with none)."""
    med = row_median(values)
    dev = np.abs(values - med[:, None])
    keep = dev <= np.maximum(3.0 * 1.4826 * row_median(dev), 1.0)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out: Array = np.where(keep, values, 0.0).sum(axis=1) / keep.sum(axis=1)
    return out


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


@dataclass(frozen=True, eq=False)
class _Curves:
    """Curves fitted to lines' points, one a line: origin, direction and normal (L, 2),
    the offset along the normal as a quadratic in the distance along the direction
    (coefficients (L, 3), highest first), the RMS (L,) and whether the line was fitted."""

    origin: Array
    direction: Array
    normal: Array
    coef: Array
    rms: Array
    fitted: NDArray[np.bool_]


def _curves(pts: Array, mask: NDArray[np.bool_], quadratic: NDArray[np.bool_]) -> _Curves:
    """Curves fitted to lines' points (L, P, 2) where ``mask``, all lines at once: a
    parabola (in pixels, along the line's principal direction) through a line whose two
    edges were measured (``quadratic``), a straight line through one (least squares, by
    the normal equations in the scaled distance along the line). Points beyond
    ``REJECT_SIGMA`` robust σ are dropped (two passes); a line with fewer than
    ``MIN_LINE_POINTS`` points is not fitted."""
    n_l = len(pts)
    count = mask.sum(axis=1)
    fitted = count >= MIN_LINE_POINTS
    origin = np.where(mask[..., None], pts, 0.0).sum(axis=1) / np.maximum(count, 1)[:, None]
    x = np.where(mask[..., None], pts - origin[:, None, :], 0.0)
    scatter = x.transpose(0, 2, 1) @ x
    theta = 0.5 * np.arctan2(2.0 * scatter[:, 0, 1], scatter[:, 0, 0] - scatter[:, 1, 1])
    direction = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    s = (x * direction[:, None, :]).sum(axis=2)
    n = (x * normal[:, None, :]).sum(axis=2)
    # fitted in s over its largest |s|, which keeps the normal equations well conditioned
    scale = np.maximum(np.abs(s).max(axis=1), 1e-9)
    u = s / scale[:, None]
    A = np.stack([np.where(quadratic[:, None], u * u, 0.0), u, np.ones_like(u)], axis=2)
    keep = mask.copy()
    c, r = np.zeros((n_l, 3)), np.zeros(s.shape)
    for _ in range(3):
        wa = A * keep[..., None]
        M = wa.transpose(0, 2, 1) @ A
        M[~quadratic, 0, 0] = 1.0  # a straight line: no square term
        fitted &= np.linalg.det(M) != 0
        M[~fitted] = np.eye(3)
        c = np.linalg.solve(M, (wa * n[..., None]).sum(axis=1)[..., None])[..., 0]
        r = n - ((c[:, :1] * u + c[:, 1:2]) * u + c[:, 2:])
        mad = 1.4826 * row_median(np.where(keep, np.abs(r), np.nan))
        new = mask & (np.abs(r) <= np.maximum(REJECT_SIGMA * mad, 1e-6)[:, None])
        done = (new.sum(axis=1) < MIN_LINE_POINTS) | (new == keep).all(axis=1)
        keep = np.where(done[:, None], keep, new)  # a done line's next pass repeats its last
    rms = np.sqrt(np.where(keep, r**2, 0.0).sum(axis=1) / np.maximum(keep.sum(axis=1), 1))
    coef = c / np.stack([scale**2, scale, np.ones(n_l)], axis=1)
    return _Curves(origin, direction, normal, coef, rms, fitted)


def _meet(curves: _Curves, guess: Array) -> tuple[Array, NDArray[np.bool_], Array]:
    """Where the curves fitted to the two lines through each corner meet (lines 2k and
    2k + 1 are corner k's; Newton's method from ``guess`` (C, 2), px); whether they do
    (both lines fitted, meeting within 3 px of the guess); the larger of their RMS."""
    n_c = len(guess)
    o, d, nrm, c = (
        a.reshape(n_c, 2, -1) for a in (curves.origin, curves.direction, curves.normal, curves.coef)
    )
    ok = curves.fitted.reshape(n_c, 2).all(axis=1)
    p = np.asarray(guess, dtype=np.float64).copy()
    going = ok.copy()
    with np.errstate(all="ignore"):  # a corner whose curves barely cross may run off
        for _ in range(8):
            rel = p[:, None, :] - o
            s, n = (rel * d).sum(axis=2), (rel * nrm).sum(axis=2)
            F = n - ((c[..., 0] * s + c[..., 1]) * s + c[..., 2])
            J = nrm - (2.0 * c[..., 0] * s + c[..., 1])[..., None] * d  # row k: curve k
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            stuck = going & ~(np.abs(det) > 0)
            ok &= ~stuck
            going &= ~stuck
            # J dp = −F by Cramer's rule
            dx = (J[:, 0, 1] * F[:, 1] - J[:, 1, 1] * F[:, 0]) / det
            dy = (J[:, 1, 0] * F[:, 0] - J[:, 0, 0] * F[:, 1]) / det
            dp = np.stack([dx, dy], axis=1)
            p = np.where(going[:, None], p + dp, p)
            going &= ~(np.hypot(dp[:, 0], dp[:, 1]) < 1e-9)
            if not going.any():
                break
    ok &= np.isfinite(p).all(axis=1) & (np.hypot(*(p - guess).T) <= 3.0)
    return p, ok, curves.rms.reshape(n_c, 2).max(axis=1)
