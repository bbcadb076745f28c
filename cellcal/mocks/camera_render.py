"""What the simulated cell's cameras see: marker targets and ChArUco boards rendered
through each camera's model.

The renderer is the twin's sensor, so its own bias must sit far below what the detector
is meant to reach (0.06 px):

* every face is a plane with an exact, analytic texture (marker bits, a white plate
  around them, or a ChArUco board's squares): edges are sharp, not a resampled bitmap;
* each pixel integrates its area: ``supersample``² sub-pixel rays per pixel in an
  n-rooks pattern (each on its own row and column, so edges along the pixel grid are
  resolved to 1/s² px), box-filtered; pixel centres sit at integer coordinates, so
  pixel ``u`` covers ``[u − ½, u + ½)``; only pixels the scene changes in are
  sampled so (:func:`render_region`: the rest take the level at their corners);
* rays leave the camera through its distortion: the pixel grid is undistorted (OpenCV,
  100 iterations) at the pixel corners and interpolated inside each pixel, where the
  distortion is smooth to far below a thousandth of a pixel;
* then lens blur (Gaussian, σ in px), then sensor noise per frame (Gaussian, grey
  levels), quantised to 8 bits with saturation.

One clean render per camera per pose (:meth:`SceneRenderer.clean`); a frame adds fresh
noise to it (:func:`exposed`), as a camera's successive frames of a still target do.
Faces turned away from a camera, or seen more obliquely than ``max_incidence_deg``, are
not drawn; faces that overlap in the image hide each other through a depth buffer over
the sub-pixel samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.camera_rig import Board, Camera, Marker, Target
from cellcal.calib.geometry import Array, invert

#: An image (float32 grey levels, or 8-bit frames).
Image = NDArray[Any]

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
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


def _bits(dictionary: str, marker_id: int) -> Array:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    n = int(d.markerSize) + 2
    img = cv2.aruco.generateImageMarker(d, marker_id, n, borderBits=1)
    out: Array = (img > 127).astype(np.float32)
    return out


def target_faces(target: Target, margin: float) -> tuple[Face, ...]:
    """One face per marker of a target: the marker on its white plate."""
    faces = []
    for m in target.markers:
        faces.append(_marker_face(m, target.dictionary, margin))
    return tuple(faces)


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


def _shade(face: Face, qx: Array, qy: Array, optics: Optics) -> tuple[Image, Image]:
    """Coverage mask and grey level of face points (qx, qy)."""
    on = (qx >= face.x0) & (qx < face.x1) & (qy >= face.y0) & (qy < face.y1)
    white = np.ones(qx.shape, dtype=np.float32)
    if face.checker > 0.0:
        i = np.floor(qx / face.checker).astype(np.int64)
        j = np.floor(qy / face.checker).astype(np.int64)
        white = ((i + j) % 2 == 1).astype(np.float32)
    if face.cell_patch is not None:  # a board: each square holds at most one marker
        _shade_board(face, qx, qy, on, white)
    else:
        for p in face.patches:
            _shade_patch(p, qx, qy, np.ones(qx.shape, dtype=bool), white)
    grey = (optics.black + (optics.white - optics.black) * white).astype(np.float32)
    return on, grey


def _shade_patch(p: _Patch, qx: Array, qy: Array, where: Image, white: Image) -> None:
    """Paint a marker's bits into ``white`` at the points ``where`` selects."""
    n = p.bits.shape[0]
    dx, dy = qx[where] - p.origin[0], qy[where] - p.origin[1]
    a = (dx * p.ex[0] + dy * p.ex[1]) / float(p.ex @ p.ex)
    b = (dx * p.ey[0] + dy * p.ey[1]) / float(p.ey @ p.ey)
    inside = (a >= 0.0) & (a < 1.0) & (b >= 0.0) & (b < 1.0)
    if inside.any():
        col = np.clip((a[inside] * n).astype(np.int64), 0, n - 1)
        row = np.clip((b[inside] * n).astype(np.int64), 0, n - 1)
        idx = np.flatnonzero(where)[inside]
        white.reshape(-1)[idx] = p.bits[row, col]


def _shade_board(face: Face, qx: Array, qy: Array, on: Image, white: Image) -> None:
    """Paint a board's markers: each point looks up the marker of its square."""
    assert face.cell_patch is not None
    ny, nx = face.cell_patch.shape
    i = np.clip(np.floor(qx / face.checker).astype(np.int64), 0, nx - 1)
    j = np.clip(np.floor(qy / face.checker).astype(np.int64), 0, ny - 1)
    k = np.where(on, face.cell_patch[j, i], -1)
    for idx in np.unique(k[k >= 0]):
        _shade_patch(face.patches[int(idx)], qx, qy, k == idx, white)


def _subpixels(s: int) -> tuple[Array, Array]:
    """Offsets (s, s) of a pixel's sub-pixel samples from its centre, [row j, column i]:
    an "n-rooks" pattern, every sample on its own row and column of an s²-fine grid, so
    an edge along the pixel grid is still resolved to 1/s² of a pixel."""
    j, i = np.mgrid[0:s, 0:s]
    dx = (i + (j + 0.5) / s) / s - 0.5
    dy = (j + (i + 0.5) / s) / s - 0.5
    return dx, dy


class _Lens:
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

    def normalised(self, us: Array, vs: Array) -> tuple[Array, Array]:
        K = self.K
        if self.grid is None:
            return (us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1]
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


def _window(camera: Camera, face: Face, T: Array) -> tuple[int, int, int, int] | None:
    """The pixel window ``(u0, v0, u1, v1)`` a face posed at ``T`` (in the camera frame)
    covers, with a margin; None when it is behind the camera or off the image."""
    corners = np.array(
        [
            [face.x0, face.y0, 0],
            [face.x1, face.y0, 0],
            [face.x1, face.y1, 0],
            [face.x0, face.y1, 0],
        ],
        dtype=np.float64,
    )
    pts = corners @ T[:3, :3].T + T[:3, 3]
    if (pts[:, 2] <= 0).any():
        return None
    px = camera.project(pts @ camera.T_rig_cam[:3, :3].T + camera.T_rig_cam[:3, 3])
    u0 = max(math.floor(px[:, 0].min()) - 2, 0)
    v0 = max(math.floor(px[:, 1].min()) - 2, 0)
    u1 = min(math.ceil(px[:, 0].max()) + 3, camera.width)
    v1 = min(math.ceil(px[:, 1].max()) + 3, camera.height)
    return None if u1 <= u0 or v1 <= v0 else (u0, v0, u1, v1)


#: a face posed in the camera frame, with its pixel window
_Posed = tuple[Face, Array, tuple[int, int, int, int]]


def _trace(lens: _Lens, todo: list[_Posed], us: Array, vs: Array, optics: Optics) -> Image:
    """Grey levels of the scene at sample points ``us, vs`` (N, m): row n holds samples
    of one place (a pixel, or one check point), which a face's window selects whole.
    Faces hide each other sample by sample (depth test)."""
    depth = np.full(us.shape, np.inf)
    grey = np.full(us.shape, optics.background, dtype=np.float32)
    cu, cv = us.mean(axis=1), vs.mean(axis=1)
    for face, T, (u0, v0, u1, v1) in todo:
        inside = (cu >= u0 - 0.5) & (cu <= u1 - 0.5) & (cv >= v0 - 0.5) & (cv <= v1 - 0.5)
        if not inside.any():
            continue
        sel = slice(None) if inside.all() else np.flatnonzero(inside)
        R, t = T[:3, :3], T[:3, 3]
        x, y = lens.normalised(us[sel], vs[sel])
        # ray (x, y, 1)·λ meets the plane through t with normal R[:, 2]
        n = R[:, 2]
        lam = float(n @ t) / (n[0] * x + n[1] * y + n[2])
        px_, py_, pz_ = lam * x - t[0], lam * y - t[1], lam - t[2]
        qx = R[0, 0] * px_ + R[1, 0] * py_ + R[2, 0] * pz_
        qy = R[0, 1] * px_ + R[1, 1] * py_ + R[2, 1] * pz_
        on, value = _shade(face, qx, qy, optics)
        d = depth[sel]
        nearer = on & (lam > 0) & (lam < d)
        depth[sel] = np.where(nearer, lam, d)
        grey[sel] = np.where(nearer, value, grey[sel])
    return grey


def _changing(check: Array, k: int) -> Image:
    """Pixels the scene changes in, from its levels on a grid of ``k`` check points per
    pixel side, pixel corners included ((k·h + 1, k·w + 1)): a straight edge through a
    pixel always parts its corners, and a feature wider than 1/k px meets a point."""
    if k == 1:
        quad = (check[:-1, :-1], check[:-1, 1:], check[1:, :-1], check[1:, 1:])
        out: Image = np.maximum.reduce(quad) > np.minimum.reduce(quad)
        return out
    blocks = np.lib.stride_tricks.sliding_window_view(check, (k + 1, k + 1))[::k, ::k]
    changing: Image = blocks.max(axis=(2, 3)) > blocks.min(axis=(2, 3))
    return changing


def _check_points_per_px(camera: Camera, todo: list[_Posed]) -> int:
    """Check points per pixel side so that the smallest feature of any face (a marker's
    bit, foreshortened) is wider than their spacing: 1 for the flange target at 1.25 m,
    more for small or steeply tilted board squares."""
    f = float(min(camera.K[0, 0], camera.K[1, 1]))
    smallest = math.inf
    for face, T, _ in todo:
        cell = min(
            (min(np.linalg.norm(p.ex), np.linalg.norm(p.ey)) / p.bits.shape[0])
            for p in face.patches
        )
        if face.checker > 0.0:
            cell = min(cell, face.checker)
        far = max(float(T[2, 3]), 1e-9) + 0.5 * math.hypot(face.x1 - face.x0, face.y1 - face.y0)
        cos = abs(float(T[:3, 2] @ T[:3, 3])) / float(np.linalg.norm(T[:3, 3]))
        smallest = min(smallest, f * cell / far * cos)
    return int(min(max(math.ceil(1.25 / max(smallest, 1e-9)), 1), 8))


def _outlines(camera: Camera, todo: list[_Posed], u0: int, v0: int, w: int, h: int) -> Image:
    """The window's pixels a face's outline runs through, with a pixel to spare: where
    faces meet, slivers of background or of the face behind may be thinner than any
    check point's spacing."""
    mask = np.zeros((h, w), dtype=np.uint8)
    t = np.linspace(0.0, 1.0, 9)[:-1, None]
    for face, T, _ in todo:
        c = np.array(
            [[face.x0, face.y0], [face.x1, face.y0], [face.x1, face.y1], [face.x0, face.y1]]
        )
        ring = np.concatenate([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        pts = np.column_stack([ring, np.zeros(len(ring))]) @ T[:3, :3].T + T[:3, 3]
        px = camera.project(pts @ camera.T_rig_cam[:3, :3].T + camera.T_rig_cam[:3, 3])
        fixed = np.rint((px - [u0, v0]) * 16).astype(np.int32)
        cv2.polylines(mask, [fixed], isClosed=True, color=1, thickness=2, shift=4)
    out: Image = mask > 0
    return out


def _sampled(
    lens: _Lens, todo: list[_Posed], rows: Image, cols: Image, s: int, optics: Optics
) -> Image:
    """The ``s``² sub-pixel samples (N, s²) of the window's pixels ``rows, cols``."""
    dx, dy = _subpixels(s)
    us = (lens.u0 + cols)[:, None] + dx.reshape(1, -1)
    vs = (lens.v0 + rows)[:, None] + dy.reshape(1, -1)
    return _trace(lens, todo, us, vs, optics)


#: A part of an image: (rows, columns).
Region = tuple[slice, slice]


def render(camera: Camera, faces: tuple[Face, ...], T_rig_obj: Array, optics: Optics) -> Image:
    """The clean image (float32 grey levels, blurred, no noise) of an object's faces
    posed at ``T_rig_obj``, as ``camera`` sees it (:func:`render_region` on the plain
    background)."""
    img: Image = np.full((camera.height, camera.width), optics.background, dtype=np.float32)
    part, region = render_region(camera, faces, T_rig_obj, optics)
    img[region] = part
    return img


def render_region(
    camera: Camera, faces: tuple[Face, ...], T_rig_obj: Array, optics: Optics
) -> tuple[Image, Region]:
    """The part of the clean image that is not plain background, and where it is in the
    image (an empty region when the camera sees none of the faces).

    Each pixel is the mean of its ``supersample``² sub-pixel samples, but only where the
    scene changes inside it. The window the faces cover is first traced at check points
    (the pixels' corners, and between them where the smallest feature is narrower than
    1.25 px). A pixel whose check points differ, or that a face's outline runs through,
    is sampled; a neighbour of one is probed with a quarter of the samples and sampled
    when any differs; every other pixel takes its check points' level, which all its
    samples would have had. Only a feature's corner that pokes into a pixel between the
    probes is missed: in a few pixels of an image, at bits' corners (not what is
    measured), by under a tenth of the black-white step before the blur. With
    ``optics.adaptive`` off every pixel is sampled: the same image up to such pokes,
    three to four times slower.
    """
    W, H, s = camera.width, camera.height, optics.supersample
    T_cam_obj = invert(camera.T_rig_cam) @ T_rig_obj
    cos_max = math.cos(math.radians(optics.max_incidence_deg))
    todo: list[_Posed] = []
    for face in faces:
        T = T_cam_obj @ face.T_obj_face
        normal = face.front * T[:3, 2]
        view = -T[:3, 3] / np.linalg.norm(T[:3, 3])
        if float(normal @ view) < cos_max:
            continue
        win = _window(camera, face, T)
        if win is not None:
            todo.append((face, T, win))
    if not todo:
        return np.zeros((0, 0), dtype=np.float32), (slice(0, 0), slice(0, 0))
    U0, V0 = min(t[2][0] for t in todo), min(t[2][1] for t in todo)
    U1, V1 = max(t[2][2] for t in todo), max(t[2][3] for t in todo)
    w, h = U1 - U0, V1 - V0
    lens = _Lens(camera, U0, V0, w, h)
    if optics.adaptive:
        k = _check_points_per_px(camera, todo)
        gv, gu = np.mgrid[0 : k * h + 1, 0 : k * w + 1]
        us, vs = (U0 - 0.5 + gu / k).reshape(-1, 1), (V0 - 0.5 + gv / k).reshape(-1, 1)
        check = _trace(lens, todo, us, vs, optics).reshape(k * h + 1, k * w + 1)
        window = np.ascontiguousarray(check[:-1:k, :-1:k])
        full = _changing(check, k) | _outlines(camera, todo, U0, V0, w, h)
        # a feature's corner may poke into a pixel without reaching its check points, but
        # not past its neighbour's edges: the neighbours of changing pixels are probed
        near = (cv2.dilate(full.astype(np.uint8), _CROSS) > 0) & ~full
        rn, cn = np.nonzero(near)
        if rn.size:
            probe = _sampled(lens, todo, rn, cn, max(s // 2, 2), optics)
            poked = (probe != window[rn, cn][:, None]).any(axis=1)
            full[rn[poked], cn[poked]] = True
        rows, cols = np.nonzero(full)
    else:
        window = np.empty((h, w), dtype=np.float32)
        rows, cols = (a.ravel() for a in np.mgrid[0:h, 0:w])
    if rows.size:
        window[rows, cols] = _sampled(lens, todo, rows, cols, s, optics).mean(axis=1)
    if optics.blur_px <= 0:
        return window, (slice(V0, V1), slice(U0, U1))
    # the blur reaches a few σ beyond the window, into the plain background (which it
    # leaves as it is)
    m = math.ceil(4.0 * optics.blur_px) + 2
    r0, c0 = max(V0 - m, 0), max(U0 - m, 0)
    region = (slice(r0, min(V1 + m, H)), slice(c0, min(U1 + m, W)))
    part = np.full((region[0].stop - r0, region[1].stop - c0), optics.background, np.float32)
    part[V0 - r0 : V1 - r0, U0 - c0 : U1 - c0] = window
    blurred: Image = cv2.GaussianBlur(part, (0, 0), optics.blur_px, borderType=cv2.BORDER_REPLICATE)
    return blurred, region


def exposed(clean: Image, rng: np.random.Generator, noise_grey: float) -> Image:
    """One 8-bit frame: the clean image plus fresh Gaussian noise, rounded, saturated."""
    noise = rng.standard_normal(clean.shape, dtype=np.float32)
    if noise_grey != 1.0:
        noise *= np.float32(noise_grey)
    frame: Image = cv2.add(clean, noise, dtype=cv2.CV_8U)
    return frame


class SceneRenderer:
    """Renders a target (or a board) for every camera of a rig."""

    def __init__(self, cameras: tuple[Camera, ...], faces: tuple[Face, ...], optics: Optics):
        self.cameras = cameras
        self.faces = faces
        self.optics = optics

    @classmethod
    def for_target(
        cls, cameras: tuple[Camera, ...], target: Target, optics: Optics | None = None
    ) -> SceneRenderer:
        o = optics or Optics()
        return cls(cameras, target_faces(target, o.margin), o)

    @classmethod
    def for_board(
        cls, cameras: tuple[Camera, ...], board: Board, optics: Optics | None = None
    ) -> SceneRenderer:
        return cls(cameras, (board_face(board),), optics or Optics())

    def clean(self, T_rig_obj: Array) -> dict[str, Image]:
        """One clean image per camera of the object at ``T_rig_obj``."""
        return {c.name: render(c, self.faces, T_rig_obj, self.optics) for c in self.cameras}

    def frames(self, clean: dict[str, Image], rng: np.random.Generator) -> dict[str, Image]:
        """One noisy 8-bit frame per camera."""
        return {k: exposed(v, rng, self.optics.noise_grey) for k, v in clean.items()}
