"""Marker corners to a few hundredths of a pixel: find markers with OpenCV's
``ArucoDetector``, then locate each corner from its two edges.

OpenCV's own corner refiners are biased by 0.2–0.5 px on blurred images (SUBPIX moves
the corner toward the marker's inside, CONTOUR follows the thresholded contour). Here each
of a marker's four border edges is sampled across its length: the edge crosses each row
(or column) of pixels where the window's summed grey levels split between the dark and
the bright level (see :func:`edge_points`). The points are undistorted (points, never
the image) and a straight line is fitted to them in normalised coordinates, where the
pinhole model keeps edges straight; adjacent lines meet at the corner. The ends of each
edge, where the neighbouring edge bends the profile, are left out. All markers of an
image are measured together (numpy over padded arrays).

Measured on the camera twin's images (40 mm markers at 1.25 m, f = 1000 px, blur 0.8 px,
noise 2 grey levels): 0.02 px RMS per corner, unbiased, where CORNER_REFINE_SUBPIX gives
0.35–0.41 px. Limits: the black border must be at least :data:`MIN_BORDER_PX` wide in
the image, and the lens blur well below a fifth of it (at 1.5 px blur the error grows to
0.07–0.09 px).

Pure numerics: an image and a :class:`~cellcal.calib.camera_rig.Camera` in, corners in
normalised coordinates out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.camera_rig import Camera
from cellcal.calib.geometry import Array
from cellcal.errors import InputError

#: Fraction of each edge used (its ends are bent by the neighbouring edge).
EDGE_SPAN = (0.18, 0.82)
#: Largest half-width of the window across an edge, in pixels along the scanline.
WINDOW_HALF_PX = 6.0
#: How far a blurred edge reaches (about 2σ of a 0.8 px lens blur with the pixel's own
#: width): the window stays this far from the marker's inner bits, px.
BLUR_REACH_PX = 1.8
#: Narrowest black border (one bit of the marker) that is measured, px.
MIN_BORDER_PX = 4.0
#: Passes over each edge: the detector's corners are off by up to a pixel, so the window
#: and the level probes are placed again on each pass's estimate.
PASSES = 3
#: Passes for a followed marker: its expected corners are within a tenth of a pixel.
FOLLOW_PASSES = 2
#: Least difference between the bright and the dark grey level of an edge.
MIN_CONTRAST = 20.0
#: Fewest edge points a line is fitted to.
MIN_EDGE_POINTS = 5


@dataclass(frozen=True)
class Window:
    """A rectangle of the image ``[x0, x1) × [y0, y1)`` in pixels."""

    x0: int
    y0: int
    x1: int
    y1: int


#: An image or a grey-level array of any pixel type.
Image = NDArray[Any]

#: The sub-pixel points of a marker's four edges, px.
Edges = tuple[Array, Array, Array, Array]


@dataclass(frozen=True, eq=False)
class MarkerImage:
    """One marker found in one image: the detector's corners (4, 2) in px, in its order
    (top-left, top-right, bottom-right, bottom-left of the marker), and the sub-pixel
    points of each edge (edge k runs from corner k to corner k+1), px."""

    id: int
    corners_px: Array
    edges_px: Edges


def grey(image: Image) -> Image:
    """A colour image (BGR/BGRA, as OpenCV reads it) as grey of the same bit depth; a
    grey one (also (h, w, 1)) as it is."""
    a: Image = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        out: Image = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        return out
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    return a


def grey_levels(image: Image) -> tuple[Image, Image]:
    """An image as (8-bit grey for the detector, grey for the edges: the 8-bit image
    itself, or float32 in 8-bit units for a 16-bit one). Accepts 8- or 16-bit, grey or
    colour (BGR/BGRA as OpenCV reads them)."""
    a = grey(image)
    if a.ndim != 2 or a.size == 0:
        raise InputError(f"not a grey or colour image (shape {a.shape})")
    if a.dtype == np.uint8:
        return a, a
    if a.dtype == np.uint16:
        return (a >> 8).astype(np.uint8), a.astype(np.float32) / 256.0
    raise InputError(f"unsupported pixel type {a.dtype} (8- or 16-bit expected)")


class MarkerFinder:
    """Finds the markers of one dictionary (optionally only some ids) in an image."""

    def __init__(self, dictionary: str, ids: frozenset[int] | None = None) -> None:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._detector = cv2.aruco.ArucoDetector(d, params)
        self._bits = int(d.markerSize) + 2
        self.ids = ids

    def find(self, image: Image, window: Window | None = None) -> list[MarkerImage]:
        """The markers in ``image`` (or in a window of it), each with its edge points."""
        grey8, grey = grey_levels(image)
        x0 = y0 = 0
        search = grey8
        if window is not None:
            h, w = grey8.shape
            x0, y0 = max(window.x0, 0), max(window.y0, 0)
            x1, y1 = min(window.x1, w), min(window.y1, h)
            if x1 - x0 < 8 or y1 - y0 < 8:
                return []
            search = grey8[y0:y1, x0:x1]
        corners, ids, _ = self._detector.detectMarkers(search)
        if ids is None:
            return []
        keep = [
            (int(i), c.reshape(4, 2).astype(np.float64) + np.array([x0, y0]))
            for c, i in zip(corners, ids.ravel(), strict=True)
            if self.ids is None or int(i) in self.ids
        ]
        if not keep:
            return []
        return self._measure(grey, [k for k, _ in keep], np.array([c for _, c in keep]))

    def follow(self, image: Image, ids: list[int], corners_px: Array) -> list[MarkerImage]:
        """Markers already identified, measured where they are expected (``corners_px``
        (m, 4, 2), within a pixel or two) without running the detector: a still target
        filmed again. Markers whose edges are not found there are left out."""
        return self.follow_many([image], [(ids, corners_px)])[0]

    def follow_many(
        self, images: Sequence[Image], expected: Sequence[tuple[list[int], Array]]
    ) -> list[list[MarkerImage]]:
        """:meth:`follow` in several images at once (one set of cameras): the same
        numbers, a quarter of the work for four cameras."""
        greys = [grey_levels(image)[1] for image in images]
        ids = [e[0] for e in expected]
        corners = [e[1] for e in expected]
        edges = _edge_points(greys, corners, self._bits, FOLLOW_PASSES)
        return [_found(i, c, e) for i, c, e in zip(ids, corners, edges, strict=True)]

    def _measure(
        self, grey: Image, ids: list[int], corners_px: Array, passes: int = PASSES
    ) -> list[MarkerImage]:
        return _found(ids, corners_px, edge_points(grey, corners_px, self._bits, passes))


def _found(ids: list[int], corners_px: Array, edges: list[Edges | None]) -> list[MarkerImage]:
    return [
        MarkerImage(mid, c, e)
        for mid, c, e in zip(ids, corners_px, edges, strict=True)
        if e is not None
    ]


def edge_points(
    grey: Image, corners_px: Array, bits: int, passes: int = PASSES
) -> list[Edges | None]:
    """Sub-pixel points on the 4 edges of each marker whose approximate corners are
    ``corners_px`` (m, 4, 2); None for a marker with an edge too short, too faint or too
    near the image's border to measure.

    Each point is where the edge crosses the centre line of one pixel row (or column,
    whichever crosses the edge more squarely), found from the grey levels' sum over a
    short window across the edge: the window's area splits between the dark level (the
    middle of the black border) and the bright one (as far outside). Pixels integrate
    area and the lens blur is symmetric, so for a straight edge this is exact up to
    noise, with no interpolation between pixels. The window is centred on a first
    estimate and the sum taken again.
    """
    return _edge_points([grey], [corners_px], bits, passes)[0]


def _edge_points(
    greys: Sequence[Image], corners: Sequence[Array], bits: int, passes: int
) -> list[list[Edges | None]]:
    """:func:`edge_points` of the markers ``corners[k]`` (m_k, 4, 2) in image ``greys[k]``,
    all images' markers in one pass of numpy (the per-call cost, not the pixels, is what
    a few markers per image cost)."""
    counts = [len(c) for c in corners]
    if sum(counts) == 0:
        return [[] for _ in corners]
    corners_px = np.concatenate(
        [np.asarray(c, dtype=np.float64).reshape(-1, 4, 2) for c in corners]
    )
    owner = np.repeat(np.arange(len(corners)), [4 * n for n in counts])  # image of each edge
    h = np.array([g.shape[0] for g in greys])[owner]
    w = np.array([g.shape[1] for g in greys])[owner]
    m = corners_px.shape[0]
    a = corners_px.reshape(-1, 2)  # edge k of marker i starts at corner k ...
    b = np.roll(corners_px, -1, axis=1).reshape(-1, 2)  # ... and ends at corner k+1
    d = b - a
    length = np.linalg.norm(d, axis=1)
    border = np.repeat(length.reshape(m, 4).min(axis=1) / bits, 4)
    along = (np.abs(d[:, 0]) < np.abs(d[:, 1])).astype(np.int64)  # 0: scan columns
    idx = np.arange(len(a))
    a_al, a_ac = a[idx, along], a[idx, 1 - along]
    d_al, d_ac = d[idx, along], d[idx, 1 - along]
    cos = np.abs(d_al) / np.maximum(length, 1e-12)
    lo = np.minimum(a_al, a_al + d_al)
    span = np.abs(d_al)
    j0 = np.ceil(lo + EDGE_SPAN[0] * span).astype(np.int64)
    j1 = np.floor(lo + EDGE_SPAN[1] * span).astype(np.int64)
    count = j1 - j0 + 1
    n_j = max(int(count.max()), 1)
    js = j0[:, None] + np.arange(n_j)[None, :]
    valid = np.arange(n_j)[None, :] < count[:, None]
    e = a_ac[:, None] + (js - a_al[:, None]) * (d_ac / np.where(d_al == 0, 1, d_al))[:, None]
    centre = np.repeat(corners_px.mean(axis=1), 4, axis=0)
    c_ac = centre[idx, 1 - along]
    inward = np.where(c_ac[:, None] > e, 1.0, -1.0)[:, 0]
    # the window's half-width along the scanline: across the edge it reaches BLUR_REACH
    # short of the marker's inner bits, and at least 1.2 px
    half = np.minimum(np.maximum((border - BLUR_REACH_PX) / cos, 1.2 / cos), WINDOW_HALF_PX)
    reach = 0.5 * border / cos
    offs = np.arange(-int(WINDOW_HALF_PX) - 1, int(WINDOW_HALF_PX) + 2)
    ok_edge = (border >= MIN_BORDER_PX) & (count >= MIN_EDGE_POINTS)

    flats = [g.reshape(-1) for g in greys]
    first = np.concatenate([[0], np.cumsum([4 * n for n in counts])])  # each image's edges
    stride: Image = np.where(along == 1, w, 1)  # scan coordinate j: a row (x along) or a column
    step: Image = np.where(along == 1, 1, w)
    limit_j: Image = h * along + w * (1 - along)
    limit_i: Image = w * along + h * (1 - along)

    def gather(j: Image, i: Image) -> Array:
        """grey at scan coordinate j, across coordinate i (broadcast; edges along axis
        0); NaN outside the image, so no edge near the border is measured."""
        shape = (-1,) + (1,) * (max(j.ndim, i.ndim) - 1)
        inside = (j >= 0) & (j < limit_j.reshape(shape)) & (i >= 0) & (i < limit_i.reshape(shape))
        idx = j * stride.reshape(shape) + i * step.reshape(shape)
        out = np.empty(idx.shape, dtype=np.float64)
        for k, flat in enumerate(flats):
            part = slice(first[k], first[k + 1])
            out[part] = flat.take(idx[part], mode="clip")
        return np.where(inside, out, np.nan)

    ok = valid.copy()
    for _ in range(passes):
        # the levels: the middle of the black border, and as far outside
        probe = np.rint(e[:, :, None] + (inward * reach)[:, None, None] * np.array([1.0, -1.0]))
        ends = gather(js[:, :, None], probe.astype(np.int64))  # (E, J, 2): dark, bright
        ends = np.where(ok[:, :, None], ends, np.nan)
        dark = _row_median(ends[:, :, 0])
        bright = _row_median(ends[:, :, 1])
        left = np.where(inward < 0, dark, bright)[:, None]
        right = np.where(inward < 0, bright, dark)[:, None]
        centre_i = np.rint(e).astype(np.int64)
        # the window [e − half, e + half], centred on the estimate: its ends cut the
        # blurred edge's tails symmetrically; end pixels count by the part inside
        lo_e = e - half[:, None]
        hi_e = e + half[:, None]
        pix = centre_i[:, :, None] + offs[None, None, :]
        inside_px = np.minimum(pix + 0.5, hi_e[:, :, None]) - np.maximum(
            pix - 0.5, lo_e[:, :, None]
        )
        weight = np.minimum(np.maximum(inside_px, 0.0), 1.0)
        win = gather(js[:, :, None], pix)
        total = np.where(weight > 0, win * weight, 0.0).sum(axis=2)
        with np.errstate(all="ignore"):
            e_new = (total + left * lo_e - right * hi_e) / (left - right)
        step_ok = np.isfinite(e_new) & (np.abs(e_new - e) < half[:, None])
        ok &= step_ok
        e = np.where(step_ok, e_new, e)
    ok_edge &= np.isfinite(dark) & np.isfinite(bright) & (bright - dark >= MIN_CONTRAST)
    ok_edge &= ok.sum(axis=1) >= MIN_EDGE_POINTS
    out: list[Edges | None] = []
    for i in range(m):
        if not ok_edge[4 * i : 4 * i + 4].all():
            out.append(None)
            continue
        edges = []
        for k in range(4 * i, 4 * i + 4):
            sel = ok[k]
            pts = np.empty((int(sel.sum()), 2))
            pts[:, along[k]] = js[k, sel]
            pts[:, 1 - along[k]] = e[k, sel]
            edges.append(pts)
        out.append((edges[0], edges[1], edges[2], edges[3]))
    marker_first = np.concatenate([[0], np.cumsum(counts)])
    return [out[marker_first[k] : marker_first[k + 1]] for k in range(len(counts))]


@dataclass(frozen=True, eq=False)
class MarkerCorners:
    """A marker's corners in one camera: undistorted normalised coordinates (4, 2) in the
    detector's order, and the RMS distance of the edge points from their lines (px)."""

    id: int
    xy: Array
    edge_rms_px: float


def marker_corners(camera: Camera, markers: list[MarkerImage]) -> list[MarkerCorners]:
    """The corners where each marker's fitted edge lines meet, in normalised
    coordinates. A marker whose edge cannot be fitted, or whose adjacent edges are within
    3° of parallel, is left out."""
    return marker_corners_many([camera], [markers])[0]


def marker_corners_many(
    cameras: Sequence[Camera], markers: Sequence[list[MarkerImage]]
) -> list[list[MarkerCorners]]:
    """:func:`marker_corners` for several cameras' markers at once (one set)."""
    every = [mk for found in markers for mk in found]
    if not every:
        return [[] for _ in markers]
    n_e = 4 * len(every)
    counts = [len(e) for mk in every for e in mk.edges_px]
    n_j = max(counts)
    scaled = []
    for camera, found in zip(cameras, markers, strict=True):
        if found:
            f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
            pts = np.concatenate([e for mk in found for e in mk.edges_px])
            scaled.append(camera.normalised(pts) * f)  # px-sized units keep the fit scaled
    pts = np.zeros((n_e, n_j, 2))
    mask = np.arange(n_j)[None, :] < np.array(counts)[:, None]
    pts[mask] = np.concatenate(scaled)
    normal, c, rms, ok = _fit_lines(pts, mask)
    n1, c1 = np.roll(normal.reshape(-1, 4, 2), 1, axis=1), np.roll(c.reshape(-1, 4), 1, axis=1)
    n2, c2 = normal.reshape(-1, 4, 2), c.reshape(-1, 4)
    det = n1[..., 0] * n2[..., 1] - n1[..., 1] * n2[..., 0]
    safe = np.where(np.abs(det) < 1e-12, 1.0, det)
    x = (c1 * n2[..., 1] - c2 * n1[..., 1]) / safe
    y = (n1[..., 0] * c2 - n2[..., 0] * c1) / safe
    good: Image = np.asarray(ok.reshape(-1, 4).all(axis=1) & (np.abs(det) >= 0.05).all(axis=1))
    rms_m = np.sqrt((rms.reshape(-1, 4) ** 2).mean(axis=1))
    out: list[list[MarkerCorners]] = []
    i = 0
    for camera, found in zip(cameras, markers, strict=True):
        f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
        mine = []
        for mk in found:
            if good[i]:
                mine.append(
                    MarkerCorners(mk.id, np.stack([x[i], y[i]], axis=1) / f, float(rms_m[i]))
                )
            i += 1
        out.append(mine)
    return out


def _row_median(x: Array) -> Array:
    """The median of each row of ``x`` ignoring NaN (NaN for an all-NaN row); numpy's
    nanmedian goes through masked arrays and is ten times slower here."""
    n = np.isfinite(x).sum(axis=1)
    s = np.sort(np.where(np.isfinite(x), x, np.inf), axis=1)
    lo = np.minimum(np.maximum((n - 1) // 2, 0), x.shape[1] - 1)
    hi = np.minimum(n // 2, x.shape[1] - 1)
    rows = np.arange(x.shape[0])
    out: Array = np.where(n > 0, 0.5 * (s[rows, lo] + s[rows, hi]), np.nan)
    return out


def _fit_lines(pts: Array, mask: Image) -> tuple[Array, Array, Array, Image]:
    """Total-least-squares lines ``n·p = c`` through padded point sets (E, J, 2), three
    passes dropping points beyond 3 robust σ; (normals, offsets, RMS residuals, fitted)."""
    keep = mask.copy()
    for _ in range(3):
        wgt = keep.astype(np.float64)
        cnt = np.maximum(wgt.sum(axis=1), 1.0)
        mu = (pts * wgt[..., None]).sum(axis=1) / cnt[:, None]
        q = (pts - mu[:, None, :]) * wgt[..., None]
        sxx = (q[..., 0] ** 2).sum(axis=1)
        syy = (q[..., 1] ** 2).sum(axis=1)
        sxy = (q[..., 0] * q[..., 1]).sum(axis=1)
        theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the line's direction
        normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
        c = (normal * mu).sum(axis=1)
        r = (pts * normal[:, None, :]).sum(axis=2) - c[:, None]
        mad = 1.4826 * _row_median(np.where(keep, np.abs(r), np.nan))
        new = mask & (np.abs(r) <= np.maximum(3.0 * mad, 1e-9)[:, None])
        if np.array_equal(new, keep):
            break
        keep = new
    n_kept = keep.sum(axis=1)
    rms = np.sqrt(np.where(keep, r**2, 0.0).sum(axis=1) / np.maximum(n_kept, 1))
    return normal, c, rms, n_kept >= MIN_EDGE_POINTS
