"""Marker corners to a few hundredths of a pixel: find markers with OpenCV's
``ArucoDetector``, then locate each corner from its two edges.

OpenCV's own corner refiners are biased by 0.2–0.5 px on blurred images (SUBPIX moves
the corner toward the marker's inside, CONTOUR follows the thresholded contour). Here each
of a marker's four border edges is sampled across its length: the edge crosses each row
(or column) of pixels where the window's summed grey levels split between the dark and
the bright level (see :func:`_edge_points`). The points are undistorted (points, never
the image) and a straight line is fitted to them in normalised coordinates, where the
pinhole model keeps edges straight; adjacent lines meet at the corner. The ends of each
edge, where the neighbouring edge bends the profile, are left out. All markers of an
image are measured together (numpy over padded arrays).

Measured on the camera twin's images (40 mm markers at 1.25 m, f = 1000 px, blur 0.8 px,
noise 2 grey levels): 0.02 px RMS per corner, unbiased, where CORNER_REFINE_SUBPIX gives
0.35–0.41 px. Limits: the black border must be at least :data:`MIN_BORDER_PX` wide in
the image, and the lens blur well below a fifth of it (at 1.5 px blur the error grows to
0.07–0.09 px).

Markers are found in a window when one is given (around where they were), else in the
whole image, located first at half resolution when the target's extent is known
(:class:`MarkerFinder`). Pure numerics: an image and a
:class:`~cellcal.calib.photogrammetry.camera_rig.Camera` in, corners in normalised coordinates out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.errors import InputError

#: Fraction of each edge used (its ends are bent by the neighbouring edge).
EDGE_SPAN = (0.18, 0.82)
#: Largest half-width of the window across an edge, in pixels along the scanline.
WINDOW_HALF_PX = 6.0
#: How far a blurred edge reaches (about 2σ of a 0.8 px lens blur with the pixel's own
#: width): the window stays this far from the marker's inner bits, px.
BLUR_REACH_PX = 1.8
#: Narrowest black border (one bit of the marker) that is measured, px. Narrower ones
#: are left out, not measured worse: on the other renderer (blur σ 0.6 px) borders of
#: 3.5–4 px still give 0.022 px RMS, 3–3.5 px 0.05 px, 2.5–3 px 0.08 px; at σ 0.9 px
#: those of 3.5–4 px lean 0.015 px outward (4–4.5 px: 0.01 px), and series means with
#: them are worse (0.012 against 0.008 mm), never better (0.0046 against 0.0047 mm).
MIN_BORDER_PX = 4.0
#: Most passes over each edge: the detector's corners are off by up to a pixel, so the
#: window and the level probes are placed again on each pass's estimate ...
PASSES = 3
#: ... and for a followed marker, whose expected corners are within a tenth of a pixel.
FOLLOW_PASSES = 2
#: ... until a pass moves no edge by more than this on average, px: the window's ends then
#: cut the blurred edge's tails within a few thousandths of a pixel of symmetrically (a
#: pass leaves 2Φ(−half/σ) of its start's error: 1.4 % at a 2.2 px half-window and 0.9 px
#: of blur, far less on wider windows), so another pass would only sum other noise.
SETTLED_PX = 0.1
#: Least difference between the bright and the dark grey level of an edge.
MIN_CONTRAST = 20.0
#: The detector's adaptive-threshold windows, px: OpenCV's default adds 3 px, which only
#: serves markers far smaller than a border of MIN_BORDER_PX (and costs a third more).
THRESHOLD_WINDOWS_PX = (13, 23)
#: Growth of the target's extent seen from one marker (its perspective and tilt), and the
#: margin added, px: the window a whole image is searched in once the target is located.
LOCATE_GROWTH = 1.3
LOCATE_MARGIN_PX = 24
#: The adaptive-threshold window of the half-resolution search that only locates the
#: target, px (one window: it needs one marker, not all; half the time of two).
LOCATE_THRESHOLD_PX = 7
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


@dataclass(frozen=True, eq=False)
class MarkerImage:
    """One marker found in one image: the detector's (or the prediction's) corners (4, 2)
    in px, in its order (top-left, top-right, bottom-right, bottom-left of the marker), and
    the sub-pixel points of its four edges (edge k runs from corner k to corner k+1):
    ``points_px`` (4, J, 2) px, of which those ``measured`` (4, J) are points (the rest
    pad the edges to one length, so that markers are fitted together)."""

    id: int
    corners_px: Array
    points_px: Array
    measured: Image


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
    """Finds the markers of one dictionary (optionally only some ids) in an image.

    Given the target's ``extent`` (each marker id's size and the farthest any corner of
    the target lies from that marker's centre, mm), a whole image is searched in two
    steps: the detector runs on the image at half resolution, only to locate the target,
    then at full resolution in a window that holds the whole target seen from any marker
    found (its extent at that marker's scale, :data:`LOCATE_GROWTH`, plus
    :data:`LOCATE_MARGIN_PX`): 1.3 ms instead of 2.6 ms a 1280×1024 image of the bundled
    cell. Where the half-resolution image shows none of the target's markers the whole
    image is searched at full resolution, as without ``extent``."""

    def __init__(
        self,
        dictionary: str,
        ids: frozenset[int] | None = None,
        extent: Mapping[int, tuple[float, float]] | None = None,
    ) -> None:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        params.adaptiveThreshWinSizeMin = THRESHOLD_WINDOWS_PX[0]
        params.adaptiveThreshWinSizeMax = THRESHOLD_WINDOWS_PX[-1]
        params.adaptiveThreshWinSizeStep = max(
            THRESHOLD_WINDOWS_PX[-1] - THRESHOLD_WINDOWS_PX[0], 1
        )
        self._detector = cv2.aruco.ArucoDetector(d, params)
        params.adaptiveThreshWinSizeMin = params.adaptiveThreshWinSizeMax = LOCATE_THRESHOLD_PX
        self._locator = cv2.aruco.ArucoDetector(d, params)
        self._bits = int(d.markerSize) + 2
        self.ids = ids
        self._extent = dict(extent) if extent else None

    def _locate(self, grey8: Image) -> Window | None:
        """The window that holds the whole target, from its markers found at half
        resolution; None without ``extent`` or when none is found."""
        if self._extent is None:
            return None
        h, w = grey8.shape
        small = cv2.resize(grey8, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        corners, ids, _ = self._locator.detectMarkers(small)
        if ids is None:
            return None
        lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
        for c, i in zip(corners, ids.ravel(), strict=True):
            if int(i) not in self._extent:
                continue
            px = c.reshape(4, 2).astype(np.float64) * 2.0 + 0.5  # a half-res pixel covers two
            size, reach = self._extent[int(i)]
            side = float(np.hypot(*(px - px[[1, 2, 3, 0]]).T).max())
            r = reach * side / size * LOCATE_GROWTH + LOCATE_MARGIN_PX
            lo = np.minimum(lo, px.mean(axis=0) - r)
            hi = np.maximum(hi, px.mean(axis=0) + r)
        if not np.all(np.isfinite(lo)):
            return None
        return Window(
            int(np.floor(lo[0])), int(np.floor(lo[1])), int(np.ceil(hi[0])), int(np.ceil(hi[1]))
        )

    def find(self, image: Image, window: Window | None = None) -> list[MarkerImage]:
        """The markers in ``image`` (or in a window of it), each with its edge points."""
        return self.find_many([image], [window])[0]

    def find_many(
        self, images: Sequence[Image], windows: Sequence[Window | None]
    ) -> list[list[MarkerImage]]:
        """:meth:`find` in several images (each in its window, or whole), the markers'
        edges measured together."""
        greys, ids, corners = [], [], []
        for image, window in zip(images, windows, strict=True):
            grey8, grey = grey_levels(image)
            where = window if window is not None else self._locate(grey8)
            found = self._detect(grey8, where)
            if not found and window is None and where is not None:
                found = self._detect(grey8, None)
            greys.append(grey)
            ids.append([k for k, _ in found])
            corners.append(np.array([c for _, c in found]).reshape(-1, 4, 2))
        return _found(ids, corners, _edge_points(greys, corners, self._bits, PASSES))

    def _detect(self, grey8: Image, window: Window | None) -> list[tuple[int, Array]]:
        """The detector's markers of the target (id, corners (4, 2) px) in the 8-bit
        image, or in a window of it."""
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
        return [
            (int(i), c.reshape(4, 2).astype(np.float64) + np.array([x0, y0]))
            for c, i in zip(corners, ids.ravel(), strict=True)
            if self.ids is None or int(i) in self.ids
        ]

    def follow_many(
        self, images: Sequence[Image], expected: Sequence[tuple[list[int], Array]]
    ) -> list[list[MarkerImage]]:
        """Markers already identified, measured where they are expected (``expected``: per
        image, the ids and corners (m, 4, 2), within a pixel or two) without running the
        detector: a still target filmed again; one set's images at once. Markers whose
        edges are not found there are left out."""
        greys = [grey_levels(image)[1] for image in images]
        corners = [np.asarray(e[1], dtype=np.float64).reshape(-1, 4, 2) for e in expected]
        edges = _edge_points(greys, corners, self._bits, FOLLOW_PASSES)
        return _found([e[0] for e in expected], corners, edges)


#: Edge points of markers in several images, padded: points (4m, J, 2) px, which are
#: measured (4m, J), and which markers are measured (m,).
_Padded = tuple[Array, Image, Image]


def _found(
    ids: Sequence[list[int]], corners: Sequence[Array], edges: _Padded
) -> list[list[MarkerImage]]:
    """The measured markers of each image, as :class:`MarkerImage` (views into ``edges``)."""
    pts, ok, good = edges
    out: list[list[MarkerImage]] = []
    i = 0
    for mine, c in zip(ids, corners, strict=True):
        found = []
        for k, mid in enumerate(mine):
            if good[i + k]:
                e = slice(4 * (i + k), 4 * (i + k) + 4)
                found.append(MarkerImage(mid, c[k], pts[e], ok[e]))
        i += len(mine)
        out.append(found)
    return out


def _edge_points(
    greys: Sequence[Image], corners: Sequence[Array], bits: int, passes: int
) -> _Padded:
    """Sub-pixel points on the 4 edges of each marker ``corners[k]`` (m_k, 4, 2) (its
    approximate corners) in image ``greys[k]``, all images' markers in one pass of numpy
    (the per-call cost, not the pixels, is what a few markers cost), padded; a marker is
    not measured when an edge is too short, too faint or too near the image's border, or
    its border narrower than :data:`MIN_BORDER_PX` (then not even tried).

    Each point is where the edge crosses the centre line of one pixel row (or column,
    whichever crosses the edge more squarely), found from the grey levels' sum over a
    short window across the edge: the window's area splits between the dark level (the
    middle of the black border) and the bright one (as far outside). Pixels integrate
    area and the lens blur is symmetric, so for a straight edge this is exact up to
    noise, with no interpolation between pixels. The window is centred on the estimate
    and the sum taken again, until the edges settle (:data:`SETTLED_PX`)."""
    cs = [np.asarray(c, dtype=np.float64).reshape(-1, 4, 2) for c in corners]
    every = np.concatenate(cs) if cs else np.zeros((0, 4, 2))
    sel = _sides(every).min(axis=1) / bits >= MIN_BORDER_PX
    if sel.all():
        return _measure_edges(greys, cs, bits, passes)
    at = np.cumsum([0] + [len(c) for c in cs]).tolist()
    picked = [c[sel[at[k] : at[k + 1]]] for k, c in enumerate(cs)]
    sub = _measure_edges(greys, picked, bits, passes)
    pts = np.zeros((4 * len(sel), *sub[0].shape[1:]))
    ok = np.zeros((4 * len(sel), sub[1].shape[1]), dtype=bool)
    good = np.zeros(len(sel), dtype=bool)
    pts[np.repeat(sel, 4)], ok[np.repeat(sel, 4)], good[sel] = sub
    return pts, ok, good


def _sides(corners_px: Array) -> Array:
    """The lengths of each marker's four sides (m, 4), px."""
    d = corners_px[:, [1, 2, 3, 0]] - corners_px
    out: Array = np.hypot(d[..., 0], d[..., 1])
    return out


def _measure_edges(
    greys: Sequence[Image], corners: Sequence[Array], bits: int, passes: int
) -> _Padded:
    counts = [len(c) for c in corners]
    if sum(counts) == 0:
        return np.zeros((0, 1, 2)), np.zeros((0, 1), dtype=bool), np.zeros(0, dtype=bool)
    corners_px = np.concatenate(
        [np.asarray(c, dtype=np.float64).reshape(-1, 4, 2) for c in corners]
    )
    owner = np.repeat(np.arange(len(corners)), [4 * n for n in counts])  # image of each edge
    h = np.array([g.shape[0] for g in greys])[owner]
    w = np.array([g.shape[1] for g in greys])[owner]
    m = corners_px.shape[0]
    a = corners_px.reshape(-1, 2)  # edge k of marker i starts at corner k ...
    b = corners_px[:, [1, 2, 3, 0]].reshape(-1, 2)  # ... and ends at corner k+1
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
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
    # the marker's inside: the side of the edge its centre is on, along the centre's scanline
    slope = d_ac / np.where(d_al == 0, 1, d_al)
    on_edge = a_ac + (centre[idx, along] - a_al) * slope
    inward = np.where(centre[idx, 1 - along] > on_edge, 1.0, -1.0)
    # the window's half-width along the scanline: across the edge it reaches BLUR_REACH
    # short of the marker's inner bits, and at least 1.2 px
    half = np.minimum(np.maximum((border - BLUR_REACH_PX) / cos, 1.2 / cos), WINDOW_HALF_PX)
    reach = 0.5 * border / cos
    r = int(np.ceil(half.max())) + 1  # pixels beyond rint(e) ± r are outside every window
    offs = np.arange(-r, r + 1)
    ok_edge = (border >= MIN_BORDER_PX) & (count >= MIN_EDGE_POINTS)
    sides = np.array([1.0, -1.0])

    flats = [g.reshape(-1) for g in greys]
    first = np.concatenate([[0], np.cumsum([4 * n for n in counts])])  # each image's edges
    # scan coordinate j: a row (x along it) or a column; across coordinate i
    stride = np.where(along == 1, w, 1)[:, None, None]
    step = np.where(along == 1, 1, w)[:, None, None]
    limit_j = (h * along + w * (1 - along))[:, None, None]
    limit_i = (w * along + h * (1 - along))[:, None, None]
    j3 = js[:, :, None]
    row_in = (j3 >= 0) & (j3 < limit_j)
    row_at = j3 * stride

    def gather(i: Image) -> Array:
        """grey at scan coordinates js, across coordinates i (E, J, n); NaN outside the
        image, so no edge near the border is measured."""
        at = row_at + i * step
        out = np.empty(at.shape, dtype=np.float64)
        for k, flat in enumerate(flats):
            part = slice(first[k], first[k + 1])
            out[part] = flat.take(at[part], mode="clip")
        return np.where(row_in & (i >= 0) & (i < limit_i), out, np.nan)

    ok = valid.copy()
    n_e = len(a)
    for n_pass in range(passes):
        # the levels: the middle of the black border, and as far outside; and the window's
        # pixels about the estimate, in one gather
        probe = np.rint(e[:, :, None] + (inward * reach)[:, None, None] * sides)
        centre_i = np.rint(e).astype(np.int64)
        pix = centre_i[:, :, None] + offs
        vals = gather(np.concatenate([probe.astype(np.int64), pix], axis=2))
        ends = np.where(ok[:, :, None], vals[:, :, :2], np.nan)  # (E, J, 2): dark, bright
        levels = row_median(np.concatenate([ends[:, :, 0], ends[:, :, 1]]))
        dark, bright = levels[:n_e], levels[n_e:]
        left = np.where(inward < 0, dark, bright)[:, None]
        right = np.where(inward < 0, bright, dark)[:, None]
        # the window [e − half, e + half], centred on the estimate: its ends cut the
        # blurred edge's tails symmetrically; end pixels count by the part inside
        lo_e = e - half[:, None]
        hi_e = e + half[:, None]
        inside_px = np.minimum(pix + 0.5, hi_e[:, :, None]) - np.maximum(
            pix - 0.5, lo_e[:, :, None]
        )
        weight = np.clip(inside_px, 0.0, 1.0)
        total = np.where(weight > 0, vals[:, :, 2:] * weight, 0.0).sum(axis=2)
        with np.errstate(all="ignore"):
            e_new = (total + left * lo_e - right * hi_e) / (left - right)
        step_ok = np.isfinite(e_new) & (np.abs(e_new - e) < half[:, None])
        ok &= step_ok
        moved = np.where(ok, e_new - e, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
        e = np.where(step_ok, e_new, e)
        if n_pass + 1 < passes and np.abs(moved[ok_edge]).max(initial=0.0) <= SETTLED_PX:
            break
    ok_edge &= np.isfinite(dark) & np.isfinite(bright) & (bright - dark >= MIN_CONTRAST)
    ok_edge &= ok.sum(axis=1) >= MIN_EDGE_POINTS
    vertical = along[:, None] == 1
    pts = np.stack([np.where(vertical, e, js), np.where(vertical, js, e)], axis=2)
    return pts, ok, ok_edge.reshape(m, 4).all(axis=1)


def row_median(x: Array) -> Array:
    """The median of each row of ``x`` ignoring NaN (NaN for an all-NaN row); numpy's
    nanmedian goes through masked arrays and is ten times slower here."""
    n = np.isfinite(x).sum(axis=1)
    s = np.sort(np.where(np.isfinite(x), x, np.inf), axis=1)
    lo = np.minimum(np.maximum((n - 1) // 2, 0), x.shape[1] - 1)
    hi = np.minimum(n // 2, x.shape[1] - 1)
    rows = np.arange(x.shape[0])
    out: Array = np.where(n > 0, 0.5 * (s[rows, lo] + s[rows, hi]), np.nan)
    return out
