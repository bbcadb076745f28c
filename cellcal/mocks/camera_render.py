"""What the simulated cell's cameras see: marker targets and ChArUco boards rendered
through each camera's model.

The renderer is the twin's sensor, so its own bias must sit far below what the detector
is meant to reach (0.06 px):

* every face is a plane with an exact, analytic texture (marker bits, a white plate
  around them, or a ChArUco board's squares): edges are sharp, not a resampled bitmap;
* each pixel integrates its area: ``supersample``² sub-pixel rays per pixel in an
  n-rooks pattern (each on its own row and column, so edges along the pixel grid are
  resolved to 1/s² px), box-filtered; pixel centres sit at integer coordinates, so
  pixel ``u`` covers ``[u − ½, u + ½)``;
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


def _rays(camera: Camera, u0: int, v0: int, w: int, h: int, s: int) -> tuple[Array, Array]:
    """Normalised coordinates (x/z, y/z) of the ``s``² sub-pixel sample points of each
    pixel of the window ``[u0, u0 + w) × [v0, v0 + h)``, shape ``(h·s, w·s)``: sample
    ``j, i`` of pixel ``(u, v)`` at ``[v·s + j, u·s + i]``."""
    dx, dy = _subpixels(s)
    u = np.arange(u0, u0 + w, dtype=np.float64)[None, None, :, None]
    v = np.arange(v0, v0 + h, dtype=np.float64)[:, None, None, None]
    shape = (h, s, w, s)
    us = np.broadcast_to(u + dx[None, :, None, :], shape).reshape(h * s, w * s)
    vs = np.broadcast_to(v + dy[None, :, None, :], shape).reshape(h * s, w * s)
    K = camera.K
    if not np.any(camera.dist):
        return (us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1]
    # undistort the pixel corners, interpolate bilinearly inside each pixel
    cu = np.arange(u0, u0 + w + 1) - 0.5
    cv = np.arange(v0, v0 + h + 1) - 0.5
    grid = np.stack(np.meshgrid(cu, cv), axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(grid, K, camera.dist, criteria=_UNDISTORT).reshape(h + 1, w + 1, 2)
    iu = np.floor(us - (u0 - 0.5)).astype(np.int64).clip(0, w - 1)
    iv = np.floor(vs - (v0 - 0.5)).astype(np.int64).clip(0, h - 1)
    fu = us - (u0 - 0.5) - iu
    fv = vs - (v0 - 0.5) - iv
    out = []
    for c in range(2):
        g = xy[..., c]
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


def render(camera: Camera, faces: tuple[Face, ...], T_rig_obj: Array, optics: Optics) -> Image:
    """The clean image (float32 grey levels, blurred, no noise) of an object's faces
    posed at ``T_rig_obj``, as ``camera`` sees it. Faces hide each other sample by
    sample (a depth buffer over the sub-pixel samples of the window they cover)."""
    W, H, s = camera.width, camera.height, optics.supersample
    T_cam_obj = invert(camera.T_rig_cam) @ T_rig_obj
    cos_max = math.cos(math.radians(optics.max_incidence_deg))
    todo = []
    for face in faces:
        T = T_cam_obj @ face.T_obj_face
        normal = face.front * T[:3, 2]
        view = -T[:3, 3] / np.linalg.norm(T[:3, 3])
        if float(normal @ view) < cos_max:
            continue
        win = _window(camera, face, T)
        if win is not None:
            todo.append((face, T, win))
    img: Image = np.full((H, W), optics.background, dtype=np.float32)
    if todo:
        U0, V0 = min(t[2][0] for t in todo), min(t[2][1] for t in todo)
        U1, V1 = max(t[2][2] for t in todo), max(t[2][3] for t in todo)
        depth = np.full(((V1 - V0) * s, (U1 - U0) * s), np.inf, dtype=np.float32)
        grey = np.full(depth.shape, optics.background, dtype=np.float32)
        for face, T, (u0, v0, u1, v1) in todo:
            R, t = T[:3, :3], T[:3, 3]
            x, y = _rays(camera, u0, v0, u1 - u0, v1 - v0, s)
            # ray (x, y, 1)·λ meets the plane through t with normal R[:, 2]
            n = R[:, 2]
            lam = float(n @ t) / (n[0] * x + n[1] * y + n[2])
            px_, py_, pz_ = lam * x - t[0], lam * y - t[1], lam - t[2]
            qx = R[0, 0] * px_ + R[1, 0] * py_ + R[2, 0] * pz_
            qy = R[0, 1] * px_ + R[1, 1] * py_ + R[2, 1] * pz_
            on, value = _shade(face, qx, qy, optics)
            rows = slice((v0 - V0) * s, (v1 - V0) * s)
            cols = slice((u0 - U0) * s, (u1 - U0) * s)
            nearer = on & (lam > 0) & (lam < depth[rows, cols])
            depth[rows, cols] = np.where(nearer, lam, depth[rows, cols])
            grey[rows, cols] = np.where(nearer, value, grey[rows, cols])
        img[V0:V1, U0:U1] = grey.reshape(V1 - V0, s, U1 - U0, s).mean(axis=(1, 3))
    if optics.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), optics.blur_px, borderType=cv2.BORDER_REPLICATE)
    out: Image = img.astype(np.float32)
    return out


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
