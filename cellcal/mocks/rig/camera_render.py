"""What the simulated cell's cameras see: marker targets and ChArUco boards rendered
through each camera's model.

The renderer is the twin's sensor, so its own bias must sit far below what the detector
is meant to reach (0.06 px):

* every face is a plane with an exact, analytic texture (marker bits, a white plate
  around them, or a ChArUco board's squares): edges are sharp, not a resampled bitmap
  (the faces and the tracing of rays to them: ``camera_faces.py``);
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

import cv2
import numpy as np

from cellcal.calib.geometry import Array, invert
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Target
from cellcal.mocks.rig.camera_faces import (
    Face,
    Image,
    Lens,
    Optics,
    Posed,
    Rays,
    board_face,
    target_faces,
    trace,
)
from cellcal.mocks.rig.sensor_noise import gaussian_noise

__all__ = [
    "Face",
    "Image",
    "Optics",
    "Region",
    "SceneRenderer",
    "board_face",
    "exposed",
    "render",
    "render_region",
    "target_faces",
]

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def _subpixels(s: int) -> tuple[Array, Array]:
    """Offsets (s, s) of a pixel's sub-pixel samples from its centre, [row j, column i]:
    an "n-rooks" pattern, every sample on its own row and column of an s²-fine grid, so
    an edge along the pixel grid is still resolved to 1/s² of a pixel."""
    j, i = np.mgrid[0:s, 0:s]
    dx = (i + (j + 0.5) / s) / s - 0.5
    dy = (j + (i + 0.5) / s) / s - 0.5
    return dx, dy


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


def _check_points_per_px(camera: Camera, todo: list[Posed]) -> int:
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


def _rings(camera: Camera, todo: list[Posed], u0: int, v0: int, n: int = 8) -> list[Image]:
    """Each face's outline in the window (``n`` points an edge, px, 1/16 px fixed point)."""
    rings = []
    t = np.linspace(0.0, 1.0, n + 1)[:-1, None]
    for face, T, _ in todo:
        c = np.array(
            [[face.x0, face.y0], [face.x1, face.y0], [face.x1, face.y1], [face.x0, face.y1]]
        )
        ring = np.concatenate([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        pts = np.column_stack([ring, np.zeros(len(ring))]) @ T[:3, :3].T + T[:3, 3]
        px = camera.project(pts @ camera.T_rig_cam[:3, :3].T + camera.T_rig_cam[:3, 3])
        rings.append(np.rint((px - [u0, v0]) * 16).astype(np.int32))
    return rings


def _outlines(rings: list[Image], w: int, h: int) -> Image:
    """The window's pixels a face's outline runs through, with a pixel to spare: where
    faces meet, slivers of background or of the face behind may be thinner than any
    check point's spacing."""
    mask = np.zeros((h, w), dtype=np.uint8)
    for ring in rings:
        cv2.polylines(mask, [ring], isClosed=True, color=1, thickness=2, shift=4)
    out: Image = mask > 0
    return out


def _face_masks(rings: list[Image], w: int, h: int) -> list[Image]:
    """Per face, the window's pixels it may show in: inside its outline (``rings``, dense
    enough that a lens's bending of an edge between two points is far below a pixel) or
    within two pixels of it. A pixel's samples lie within 0.71 px of its centre, so a
    pixel left out has none on the face."""
    masks = []
    for ring in rings:
        mask = np.zeros((h, w), dtype=np.uint8)
        cv2.fillPoly(mask, [ring], color=1, shift=4)
        cv2.polylines(mask, [ring], isClosed=True, color=1, thickness=4, shift=4)
        masks.append(mask > 0)
    return masks


def _cover(masks: list[Image], rows: Array, cols: Array, *, grid: bool = False) -> Image:
    """Which faces may show in each of the window's pixels ``rows, cols``: (faces, N);
    with ``grid``, the pixels of the grid of those rows and columns, row after row."""
    if grid:
        at = np.ix_(rows, cols)
        return np.stack([m[at].ravel() for m in masks])
    out: Image = np.stack([m[rows, cols] for m in masks])
    return out


def _sampled(
    lens: Lens,
    todo: list[Posed],
    rows: Image,
    cols: Image,
    s: int,
    optics: Optics,
    masks: list[Image],
) -> Image:
    """The ``s``² sub-pixel samples (N, s²) of the window's pixels ``rows, cols``."""
    dx, dy = _subpixels(s)
    rays = Rays.of_pixels(lens, rows, cols, dx, dy)
    return trace(rays, todo, optics, _cover(masks, rows, cols))


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
    todo: list[Posed] = []
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
    lens = Lens(camera, U0, V0, w, h)
    rings = _rings(camera, todo, U0, V0)
    # a lens with distortion bends the faces' edges: the masks follow them closely
    dense = _rings(camera, todo, U0, V0, 64) if np.any(camera.dist) else rings
    masks = _face_masks(dense, w, h)
    if optics.adaptive:
        k = _check_points_per_px(camera, todo)
        gv, gu = np.mgrid[0 : k * h + 1, 0 : k * w + 1]
        us, vs = (U0 - 0.5 + gu / k).reshape(-1, 1), (V0 - 0.5 + gv / k).reshape(-1, 1)
        # a check point on a pixel's corner or inside it: that pixel, or its neighbour
        # (the faces' masks spare two pixels)
        near_px = (np.minimum(gv[:, 0] // k, h - 1), np.minimum(gu[0] // k, w - 1))
        cover = _cover(masks, *near_px, grid=True)
        check = trace(Rays.at(lens, us, vs), todo, optics, cover)
        check = check.reshape(k * h + 1, k * w + 1)
        window = np.ascontiguousarray(check[:-1:k, :-1:k])
        full = _changing(check, k) | _outlines(rings, w, h)
        # a feature's corner may poke into a pixel without reaching its check points, but
        # not past its neighbour's edges: the neighbours of changing pixels are probed
        near = (cv2.dilate(full.astype(np.uint8), _CROSS) > 0) & ~full
        rn, cn = np.nonzero(near)
        if rn.size:
            probe = _sampled(lens, todo, rn, cn, max(s // 2, 2), optics, masks)
            poked = (probe != window[rn, cn][:, None]).any(axis=1)
            full[rn[poked], cn[poked]] = True
        rows, cols = np.nonzero(full)
    else:
        window = np.empty((h, w), dtype=np.float32)
        rows, cols = (a.ravel() for a in np.mgrid[0:h, 0:w])
    if rows.size:
        window[rows, cols] = _sampled(lens, todo, rows, cols, s, optics, masks).mean(axis=1)
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
    noise = gaussian_noise(clean.shape, rng, noise_grey)
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
