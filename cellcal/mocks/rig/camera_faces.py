"""What a ray of the camera twin sees: the planar faces a target or a board is made of,
the camera's lens, and the grey level where a ray meets the nearest face.

The renderer (``camera_render.py``) decides which points of an image to sample; this
module traces them:

* every face is a plane with an exact, analytic texture (marker bits, a white plate
  around them, or a ChArUco board's squares): edges are sharp, not a resampled bitmap;
* a sample point's ray leaves the camera through its distortion: the pixel grid is
  undistorted (OpenCV, 100 iterations) at the pixel corners and interpolated inside each
  pixel, where the distortion is smooth to far below a thousandth of a pixel;
* a ray meets a face's plane where the face's homography (image plane → face plane)
  puts it; faces that overlap hide each other through a depth test per sample point.

The rays of a pixel's sub-pixel samples are the pixel's own plus a fixed pattern's
(:meth:`Rays.of_pixels`): without distortion, the homography of a sample is a sum of
the pixel's part and the pattern's, so each face costs a few operations a sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Target

#: An image (float32 grey levels, or 8-bit frames).
Image = NDArray[Any]

_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True)
class Optics:
    """Imaging conditions: grey levels of the scene, lens blur and sensor noise."""

    supersample: int = 8
    blur_px: float = 0.8
    noise_grey: float = 2.0
    black: float = 20.0
    white: float = 220.0
    background: float = 40.0
    #: the white plate around each marker, per side, as a fraction of the marker's edge
    margin: float = 0.25
    max_incidence_deg: float = 75.0
    #: sub-pixel samples only in pixels the scene changes in (the same image, faster)
    adaptive: bool = True


@dataclass(frozen=True)
class _Patch:
    """A marker on a face: its top-left corner and edge vectors in face coordinates,
    and its bits ((n+2)² with the black border; 0 black, 1 white)."""

    origin: Array
    ex: Array
    ey: Array
    bits: Array


@dataclass(frozen=True)
class Face:
    """A planar face: ``T_obj_face`` maps face coordinates (x, y, 0) into the object's
    frame; ``front`` is the sign of the face's z axis that points at a viewer. The face
    spans ``[x0, x1] × [y0, y1]``; ``checker`` is the square of a ChArUco board's
    chessboard (0 for none), its top-left square black."""

    T_obj_face: Array
    front: float
    x0: float
    x1: float
    y0: float
    y1: float
    patches: tuple[_Patch, ...]
    checker: float = 0.0
    #: for a board: the patch in each chessboard square (ny, nx), −1 for none
    cell_patch: Image | None = None


#: a face posed in the camera frame, with its pixel window (u0, v0, u1, v1)
Posed = tuple[Face, Array, tuple[int, int, int, int]]


def _bits(dictionary: str, marker_id: int) -> Array:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    n = int(d.markerSize) + 2
    img = cv2.aruco.generateImageMarker(d, marker_id, n, borderBits=1)
    out: Array = (img > 127).astype(np.float32)
    return out


def target_faces(target: Target, margin: float) -> tuple[Face, ...]:
    """One face per marker of a target: the marker on its white plate."""
    return tuple(_marker_face(m, target.dictionary, margin) for m in target.markers)


def _marker_face(m: Marker, dictionary: str, margin: float) -> Face:
    h = m.size / 2.0
    p = h * (1.0 + 2.0 * margin)
    # marker frame: x right, y up; the bits' rows run down, i.e. along −y
    patch = _Patch(
        origin=np.array([-h, h]),
        ex=np.array([m.size, 0.0]),
        ey=np.array([0.0, -m.size]),
        bits=_bits(dictionary, m.id),
    )
    return Face(m.T_target_marker, 1.0, -p, p, -p, p, (patch,))


def board_face(board: Board) -> Face:
    """A ChArUco board as OpenCV defines it: face coordinates x right, y down from the
    board's top-left corner, z into the board (a viewer sees it from −z)."""
    cv_board = board.cv_board()
    patches = []
    for corners, mid in zip(
        cv_board.getObjPoints(), np.asarray(cv_board.getIds()).ravel(), strict=True
    ):
        c = np.asarray(corners, dtype=np.float64)[:, :2]
        patches.append(_Patch(c[0], c[1] - c[0], c[3] - c[0], _bits(board.dictionary, int(mid))))
    nx, ny = board.squares
    cells = np.full((ny, nx), -1, dtype=np.int64)
    for k, p in enumerate(patches):
        centre = p.origin + 0.5 * (p.ex + p.ey)
        cells[int(centre[1] // board.square), int(centre[0] // board.square)] = k
    return Face(
        np.eye(4),
        -1.0,
        0.0,
        nx * board.square,
        0.0,
        ny * board.square,
        tuple(patches),
        checker=board.square,
        cell_patch=cells,
    )


# ---------------------------------------------------------------------- the lens


class Lens:
    """Pixel coordinates → normalised ones (x/z, y/z) for points of the pixel window
    ``[u0, u0 + w) × [v0, v0 + h)``. With distortion, the window's pixel corners are
    undistorted (OpenCV, 100 iterations) and points inside a pixel interpolated
    bilinearly, where the distortion is smooth to far below a thousandth of a pixel."""

    def __init__(self, camera: Camera, u0: int, v0: int, w: int, h: int) -> None:
        self.K = camera.K
        self.u0, self.v0, self.w, self.h = u0, v0, w, h
        self.grid: Image | None = None
        if np.any(camera.dist):
            cu = np.arange(u0, u0 + w + 1) - 0.5
            cv = np.arange(v0, v0 + h + 1) - 0.5
            pts = np.stack(np.meshgrid(cu, cv), axis=-1).reshape(-1, 1, 2)
            xy = cv2.undistortPoints(pts, camera.K, camera.dist, criteria=_UNDISTORT)
            self.grid = xy.reshape(h + 1, w + 1, 2)

    def normalised(
        self, us: Array, vs: Array, pixels: tuple[Array, Array] | None = None
    ) -> tuple[Array, Array]:
        """Normalised coordinates of points ``us, vs``. ``pixels``: the window row and
        column of each point's pixel (broadcast to the points), so that the grid is read
        once a pixel."""
        K = self.K
        if self.grid is None:
            return (us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1]
        if pixels is not None:  # a point inside pixel u lies in grid cell u
            iv, iu = pixels
        else:
            iu = np.floor(us - (self.u0 - 0.5)).astype(np.int64).clip(0, self.w - 1)
            iv = np.floor(vs - (self.v0 - 0.5)).astype(np.int64).clip(0, self.h - 1)
        fu = us - (self.u0 - 0.5) - iu
        fv = vs - (self.v0 - 0.5) - iv
        out = []
        for c in range(2):
            g = self.grid[..., c]
            top = g[iv, iu] * (1 - fu) + g[iv, iu + 1] * fu
            bottom = g[iv + 1, iu] * (1 - fu) + g[iv + 1, iu + 1] * fu
            out.append(top * (1 - fv) + bottom * fv)
        return out[0], out[1]


@dataclass(frozen=True)
class Rays:
    """The rays through a trace's sample points: N places (a pixel, or one check point)
    of m points each, whose centres ``cu, cv`` (N, px) the faces' windows test. ``x, y``
    (m, N: point-major, so that numpy's inner loops run along the places) are the
    points' normalised coordinates, or, with ``px, py`` (m, 1), each place's part
    (1, N) of them: a point's is its place's plus ``px, py``."""

    cu: Array
    cv: Array
    x: Array
    y: Array
    px: Array | None = None
    py: Array | None = None

    @classmethod
    def at(cls, lens: Lens, us: Array, vs: Array) -> Rays:
        """The rays through points ``us, vs`` (N, m), a place's centre its points' mean."""
        x, y = lens.normalised(us, vs)
        return cls(
            us.mean(axis=1), vs.mean(axis=1), np.ascontiguousarray(x.T), np.ascontiguousarray(y.T)
        )

    @classmethod
    def of_pixels(cls, lens: Lens, rows: Array, cols: Array, dx: Array, dy: Array) -> Rays:
        """The rays through the window's pixels ``rows, cols`` (N) at offsets ``dx, dy``
        (m) from each pixel's centre, all inside the pixel."""
        cu = (lens.u0 + cols).astype(np.float64)
        cv = (lens.v0 + rows).astype(np.float64)
        dx, dy = dx.reshape(-1, 1), dy.reshape(-1, 1)
        if lens.grid is not None:
            at = (rows[None, :], cols[None, :])
            x, y = lens.normalised(cu[None, :] + dx, cv[None, :] + dy, at)
            return cls(cu, cv, x, y)
        K = lens.K
        x, y = (cu - K[0, 2]) / K[0, 0], (cv - K[1, 2]) / K[1, 1]
        return cls(cu, cv, x[None, :], y[None, :], dx / K[0, 0], dy / K[1, 1])

    @property
    def shape(self) -> tuple[int, int]:
        """(m, N)"""
        return ((self.x if self.px is None else self.px).shape[0], len(self.cu))

    def places(self, sel: Image | slice) -> Rays:
        """The rays of places ``sel`` (indices, or a slice: a view)."""
        if isinstance(sel, slice):
            x, y = self.x[:, sel], self.y[:, sel]
        else:  # take keeps them row-major (``x[:, sel]`` would not)
            x, y = self.x.take(sel, axis=1), self.y.take(sel, axis=1)
        return Rays(self.cu[sel], self.cv[sel], x, y, self.px, self.py)

    def hom(self, m: Array) -> Array:
        """m · (x, y, 1) at every point (m, N)."""
        out: Array = m[0] * self.x + m[1] * self.y + m[2]
        if self.px is not None and self.py is not None:
            out = out + (m[0] * self.px + m[1] * self.py)
        return out


# ---------------------------------------------------------------------- tracing


def trace(rays: Rays, todo: list[Posed], optics: Optics, cover: Image | None = None) -> Image:
    """Grey levels (float32, N × m) of the scene along ``rays``. ``cover`` (faces × N)
    says which faces may show at each place (by default: the faces whose windows hold
    it); a face that shows nowhere else is traced there alone, and where several may
    show they hide each other sample by sample (depth test). The places are traced
    grouped so (each face's own places one slice of the work), then put back in order."""
    cu, cv = rays.cu, rays.cv
    if cover is None:
        cover = np.array(
            [
                (cu >= u0 - 0.5) & (cu <= u1 - 0.5) & (cv >= v0 - 0.5) & (cv <= v1 - 0.5)
                for _, _, (u0, v0, u1, v1) in todo
            ]
        ).reshape(len(todo), len(cu))
    n_faces = len(todo)
    count = cover.sum(axis=0)
    # each place's group: the one face that may show there, several (n_faces), none
    group = np.where(count == 1, cover.argmax(axis=0), n_faces + (count == 0))
    order = np.argsort(group, kind="stable")
    starts = np.searchsorted(group[order], np.arange(n_faces + 2))
    grouped = rays.places(order)
    grey = np.full(rays.shape, optics.background, dtype=np.float32)
    for f, (face, T, _) in enumerate(todo):
        alone = slice(int(starts[f]), int(starts[f + 1]))
        if alone.stop > alone.start:
            _, on, value = _meet(face, T, grouped.places(alone), optics)
            np.copyto(grey[:, alone], value, where=on)
    several = slice(int(starts[n_faces]), int(starts[n_faces + 1]))
    if several.stop > several.start:
        _nearest(grouped.places(several), todo, cover[:, order[several]], optics, grey[:, several])
    out: Image = np.empty(grey.T.shape, dtype=np.float32)
    out[order] = grey.T
    return out


def _nearest(rays: Rays, todo: list[Posed], cover: Image, optics: Optics, grey: Image) -> None:
    """Trace places several faces may show at into ``grey`` (m × N): the nearest wins."""
    depth = np.full(grey.shape, np.inf)
    for f, (face, T, _) in enumerate(todo):
        if not cover[f].any():
            continue
        whole = bool(cover[f].all())
        sel: Any = slice(None) if whole else np.flatnonzero(cover[f])
        lam, on, value = _meet(face, T, rays if whole else rays.places(sel), optics)
        d = depth[:, sel]
        nearer = on & (lam < d)
        depth[:, sel] = np.where(nearer, lam, d)
        grey[:, sel] = np.where(nearer, value, grey[:, sel])


def _meet(face: Face, T: Array, rays: Rays, optics: Optics) -> tuple[Array, Image, Image]:
    """Where ``rays`` meet the plane of ``face`` posed at ``T`` (camera frame): the
    depth λ along each ray (the point is λ·(x, y, 1)), whether the point is on the face
    in front of the camera, and its grey level."""
    # (qx, qy, 1)/λ = H⁻¹ (x, y, 1), H = [R e_x, R e_y, t]: the face plane → the camera
    M = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w = rays.hom(M[2])  # 1/λ: positive in front of the camera
        lam = 1.0 / w
        qx = rays.hom(M[0]) * lam
        qy = rays.hom(M[1]) * lam
        on = (w > 0) & (qx >= face.x0) & (qx < face.x1) & (qy >= face.y0) & (qy < face.y1)
        if face.cell_patch is None and face.checker == 0.0 and len(face.patches) == 1:
            value = _patch_levels(face.patches[0], M, rays, lam, optics)
        else:
            value = _shade(face, qx, qy, optics)
    return lam, on, value


def _patch_levels(p: _Patch, M: Array, rays: Rays, lam: Array, optics: Optics) -> Image:
    """Grey levels of a face that holds one marker, on its white plate: the marker's
    bit coordinates (column, row) come from the face's homography composed with the
    patch's affine map."""
    n = p.bits.shape[0]
    o = float(p.origin @ p.ex), float(p.origin @ p.ey)
    a_row = (p.ex[0] * M[0] + p.ex[1] * M[1] - o[0] * M[2]) * (n / float(p.ex @ p.ex))
    b_row = (p.ey[0] * M[0] + p.ey[1] * M[1] - o[1] * M[2]) * (n / float(p.ey @ p.ey))
    col = rays.hom(a_row) * lam
    row = rays.hom(b_row) * lam
    inside = (col >= 0.0) & (col < n) & (row >= 0.0) & (row < n)
    index = row.astype(np.int64) * n + col.astype(np.int64)
    levels = (optics.black + (optics.white - optics.black) * p.bits).astype(np.float32)
    out: Image = np.where(inside, levels.ravel().take(index, mode="clip"), np.float32(optics.white))
    return out


def _shade(face: Face, qx: Array, qy: Array, optics: Optics) -> Image:
    """Grey level of face points (qx, qy): a board's squares and markers, or a face's
    markers on their white plate."""
    white = np.ones(qx.shape, dtype=np.float32)
    if face.checker > 0.0:
        i = np.floor(qx / face.checker).astype(np.int64)
        j = np.floor(qy / face.checker).astype(np.int64)
        white = ((i + j) % 2 == 1).astype(np.float32)
        if face.cell_patch is not None:  # a board: each square holds at most one marker
            on = (qx >= face.x0) & (qx < face.x1) & (qy >= face.y0) & (qy < face.y1)
            _shade_board(face, qx, qy, on, i, j, white)
    if face.cell_patch is None:
        for p in face.patches:
            _shade_patch(p, qx, qy, white)
    grey: Image = (optics.black + (optics.white - optics.black) * white).astype(np.float32)
    return grey


def _shade_patch(p: _Patch, qx: Array, qy: Array, white: Image) -> None:
    """Paint a marker's bits into ``white`` at face points (qx, qy)."""
    n = p.bits.shape[0]
    dx, dy = qx - p.origin[0], qy - p.origin[1]
    a = (dx * p.ex[0] + dy * p.ex[1]) / float(p.ex @ p.ex)
    b = (dx * p.ey[0] + dy * p.ey[1]) / float(p.ey @ p.ey)
    inside = (a >= 0.0) & (a < 1.0) & (b >= 0.0) & (b < 1.0)
    if inside.any():
        col = np.clip((a[inside] * n).astype(np.int64), 0, n - 1)
        row = np.clip((b[inside] * n).astype(np.int64), 0, n - 1)
        white[inside] = p.bits[row, col]


def _shade_board(
    face: Face, qx: Array, qy: Array, on: Image, i: Image, j: Image, white: Image
) -> None:
    """Paint a board's markers into ``white``: each point on the board (``on``) looks up
    the marker of its square (``i``, ``j``), and every marker is painted in one pass,
    each point with its own marker's geometry (:func:`_shade_patch`'s numbers)."""
    assert face.cell_patch is not None
    ny, nx = face.cell_patch.shape
    k = face.cell_patch[np.clip(j, 0, ny - 1), np.clip(i, 0, nx - 1)]
    where = on & (k >= 0)
    if not where.any():
        return
    patches = face.patches
    k = k[where]

    def each(values: list[float]) -> Any:
        """One marker's value per point: a number when all the board's are the same."""
        v = np.array(values)
        return v[0] if (v == v[0]).all() else v[k]

    ox, oy = each([p.origin[0] for p in patches]), each([p.origin[1] for p in patches])
    dx, dy = qx[where] - ox, qy[where] - oy
    a = (dx * each([p.ex[0] for p in patches]) + dy * each([p.ex[1] for p in patches])) / each(
        [float(p.ex @ p.ex) for p in patches]
    )
    b = (dx * each([p.ey[0] for p in patches]) + dy * each([p.ey[1] for p in patches])) / each(
        [float(p.ey @ p.ey) for p in patches]
    )
    inside = (a >= 0.0) & (a < 1.0) & (b >= 0.0) & (b < 1.0)
    if inside.any():
        n = patches[0].bits.shape[0]  # a board's markers are all of one dictionary
        col = np.clip((a[inside] * n).astype(np.int64), 0, n - 1)
        row = np.clip((b[inside] * n).astype(np.int64), 0, n - 1)
        chosen = white[where]
        chosen[inside] = np.array([p.bits for p in patches])[k[inside], row, col]
        white[where] = chosen
