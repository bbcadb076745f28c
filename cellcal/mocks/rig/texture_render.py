"""A second, independent renderer of the photogrammetry rig's images: ChArUco boards and
marker targets as 4 GigE cameras see them, for tests and benchmarks that prove the rig on
images cellcal's own renderer (``camera_render.py``) did not make — the stand-in for a
hidden test set.

It was written from the OpenCV camera model alone, without reading ``camera_render.py``,
``mocks/rig/scene.py`` or ``mocks/rig/twin.py``, and it works differently on purpose: each
object is a
flat plate whose face is drawn once as a fine bitmap (a ChArUco board from OpenCV's own
board geometry, a marker with a white quiet zone from ``generateImageMarker``), edges on
texel boundaries; each output pixel averages a *regular* s×s grid of sub-samples, each
mapped pixel → undistorted normalised coordinates by this module's own Newton inversion of
the distortion (never ``cv2.undistortPoints``; solved at the pixel centres and
interpolated between them, 1e-5 px off) → ray/plate intersection (a homography) →
bilinear texture lookup (``cv2.remap``); the nearest plate wins (depth test). Then a
defocus disk convolved with a Gaussian blurs it, Gaussian noise (and optionally a
photo-response non-uniformity) is added and it is quantised to 8 bits.

Conventions (OpenCV's): x right, y down, z along the optical axis; pixel u covers
[u − 0.5, u + 0.5); distortion ``[k1, k2, p1, p2, k3]``; ``T_rig_cam`` maps camera
coordinates into the rig frame. Board frame: x right, y down from the top-left corner, z
into the board. Marker frame: origin at the square's centre, x right, y up, z out of the
face. The scenes (rig, poses, target) are in :mod:`cellcal.mocks.rig.texture_scenes`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Rig, Target
from cellcal.mocks.rig.sensor_noise import gaussian_noise

Array = np.ndarray
#: Sub-samples rendered at a time (keeps the arrays in cache).
_CHUNK_SAMPLES = 400_000
#: cv2.remap's limit on an image side.
_REMAP_MAX = 32000


@dataclass(frozen=True)
class Psf:
    """Lens blur: an anti-aliased defocus disk of ``disk_radius_px`` convolved with a
    Gaussian of ``gaussian_sigma_px``, integrated over each pixel cell."""

    disk_radius_px: float = 0.7
    gaussian_sigma_px: float = 0.5


@dataclass(frozen=True)
class Sensor:
    """Per-frame Gaussian noise (grey levels) and a fixed photo-response non-uniformity per
    camera (relative gain, 1σ; 0 switches it off)."""

    noise_grey: float = 2.0
    prnu: float = 0.0


@dataclass(frozen=True)
class RenderParams:
    """How a view is rendered: ``supersample`` s (s×s regular sub-samples a pixel), texture
    resolution (texels a marker bit at least), grey levels, the incidence beyond which a
    face is not drawn, blur (``None``: none) and sensor (``None``: no noise, no PRNU)."""

    supersample: int = 5
    texels_per_bit: int = 24
    black: float = 25.0
    white: float = 210.0
    background: float = 60.0
    max_incidence_deg: float = 80.0
    psf: Psf | None = field(default_factory=Psf)
    sensor: Sensor | None = field(default_factory=Sensor)


@dataclass(frozen=True, eq=False)
class TexturedPlane:
    """A flat textured plate: ``texture`` (float32 grey levels), its pose, the affine map
    ``texel_from_plane`` (3×3) from plate coordinates (mm, z = 0) to texture map
    coordinates (texel centres at integers), and the side it is seen from (``front`` +1:
    from +z, −1: from −z)."""

    texture: Array
    T_rig_plane: Array
    texel_from_plane: Array
    front: int

    def outline(self, per_edge: int = 16) -> Array:
        """Points (4·per_edge, 2) along the plate's rim, in plate coordinates (mm)."""
        h, w = self.texture.shape
        c = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
        f = np.arange(per_edge)[:, None] / per_edge
        rim = np.concatenate([c[k] + f * (c[(k + 1) % 4] - c[k]) for k in range(4)])
        inv = np.linalg.inv(self.texel_from_plane)
        out: Array = rim @ inv[:2, :2].T + inv[:2, 2]
        return out


# --- the camera model, this module's own ---------------------------------------------------


def _coefficients(dist: Array) -> tuple[float, float, float, float, float]:
    d = np.asarray(dist, dtype=np.float64).ravel()
    if d.size not in (5, 8, 12, 14) or np.any(d[5:] != 0.0):
        raise ValueError("only the distortion [k1, k2, p1, p2, k3] is rendered (others zero)")
    k1, k2, p1, p2, k3 = (float(v) for v in d[:5])
    return k1, k2, p1, p2, k3


def distort(x: Array, y: Array, dist: Array) -> tuple[Array, Array]:
    """Distorted normalised coordinates of undistorted ones (OpenCV's model)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    return (
        x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy,
    )


def undistort(xd: Array, yd: Array, dist: Array, max_iter: int = 20) -> tuple[Array, Array]:
    """Undistorted normalised coordinates of distorted ones, by Newton's method on the
    forward model (2×2 Jacobian per point), in the arrays' own float type."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    xd, yd = np.broadcast_arrays(xd, yd)
    x, y = xd.copy(), yd.copy()
    tol = 8.0 * float(np.finfo(x.dtype).eps)
    for _ in range(max_iter):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        g2 = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # 2 · d(radial)/d(r²)
        xy = x * y
        ex = xd - (x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x))
        ey = yd - (y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy)
        jxx = radial + x * x * g2 + 2.0 * p1 * y + 6.0 * p2 * x
        jyy = radial + y * y * g2 + 6.0 * p1 * y + 2.0 * p2 * x
        jxy = xy * g2 + 2.0 * p1 * x + 2.0 * p2 * y
        det = jxx * jyy - jxy * jxy
        dx = (jyy * ex - jxy * ey) / det
        dy = (jxx * ey - jxy * ex) / det
        x += dx
        y += dy
        if max(float(np.abs(dx).max()), float(np.abs(dy).max())) < tol:
            break
    return x, y


def project(camera: Camera, points_rig: Array) -> Array:
    """Pixel coordinates (n, 2) of rig points (n, 3) in front of the camera."""
    T = np.linalg.inv(camera.T_rig_cam)
    p = np.asarray(points_rig, dtype=np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    xd, yd = distort(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2], camera.dist)
    K = camera.K
    return np.column_stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def pixels_to_normalised(camera: Camera, pixels: Array) -> Array:
    """Undistorted normalised coordinates (n, 2) of pixel positions (n, 2), float64."""
    uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    K = camera.K
    x, y = undistort((uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], camera.dist)
    return np.column_stack([x, y])


# --- textures ---------------------------------------------------------------------------


def _dictionary(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _marker_bits(dictionary: str, marker_id: int, n: int) -> Array:
    """The marker with its one-bit black border, ``n`` texels a bit, 0 black 1 white."""
    d = _dictionary(dictionary)
    img = cv2.aruco.generateImageMarker(d, marker_id, d.markerSize + 2, borderBits=1)
    return np.kron((img > 127).astype(np.float32), np.ones((n, n), np.float32))


def _texels_per_bit(bit: float, lengths: tuple[float, ...], least: int) -> int:
    """The smallest n ≥ ``least`` for which every length is a whole number of texels."""
    for n in range(least, 8 * least):
        q = np.asarray(lengths) * n / bit
        if np.all(np.abs(q - np.round(q)) < 1e-6):
            return n
    raise ValueError(f"no texel size ≥ {least} a bit puts all edges on texel boundaries")


@lru_cache(maxsize=4)
def _board_texture(
    dictionary: str,
    squares: tuple[int, int],
    square: float,
    marker: float,
    legacy: bool,
    least: int,
    levels: tuple[float, float],
) -> tuple[Array, float]:
    """The board's face, one square of white margin around it, and the texel size (mm)."""
    board = Board(dictionary, squares, square, marker, legacy)
    bits = _dictionary(board.dictionary).markerSize + 2
    bit = board.marker / bits
    n = _texels_per_bit(bit, (board.square, (board.square - board.marker) / 2), least)
    t = bit / n
    per_sq = round(board.square / t)
    nx, ny = board.squares
    cv = board.cv_board()
    ids = np.asarray(cv.getIds()).ravel()
    objs = [np.asarray(o, dtype=np.float64) for o in cv.getObjPoints()]
    # markers sit on white squares; the squares' colours alternate from there
    c0 = objs[0].mean(axis=0)
    white_parity = (int(c0[0] // board.square) + int(c0[1] // board.square)) % 2
    jj, ii = np.mgrid[0:ny, 0:nx]
    cells = ((ii + jj) % 2 == white_parity).astype(np.float32)
    tex = np.ones(((ny + 2) * per_sq, (nx + 2) * per_sq), np.float32)
    tex[per_sq:-per_sq, per_sq:-per_sq] = np.kron(cells, np.ones((per_sq, per_sq), np.float32))
    for marker_id, corners in zip(ids, objs, strict=True):
        img = _marker_bits(board.dictionary, int(marker_id), n)
        c, r = (np.round(corners[0, :2] / t).astype(int) + per_sq).tolist()
        tex[r : r + img.shape[0], c : c + img.shape[1]] = img
    black, white = levels
    out = black + (white - black) * tex
    out.setflags(write=False)
    return out, t


def board_plane(board: Board, T_rig_board: Array, params: RenderParams) -> TexturedPlane:
    """The board as a plate: its face, seen from −z, one square of white margin around."""
    key = (board.dictionary, board.squares, board.square, board.marker, board.legacy)
    tex, t = _board_texture(*key, params.texels_per_bit, (params.black, params.white))
    m = board.square
    A = np.array([[1 / t, 0, m / t - 0.5], [0, 1 / t, m / t - 0.5], [0, 0, 1]])
    return TexturedPlane(tex, np.asarray(T_rig_board, dtype=np.float64), A, front=-1)


@lru_cache(maxsize=64)
def _marker_texture(
    dictionary: str, marker_id: int, n: int, quiet_bits: int, levels: tuple[float, float]
) -> Array:
    img = np.pad(_marker_bits(dictionary, marker_id, n), quiet_bits * n, constant_values=1.0)
    black, white = levels
    out: Array = black + (white - black) * img
    out.setflags(write=False)
    return out


def marker_planes(
    target: Target, T_rig_target: Array, params: RenderParams, quiet_bits: int = 2
) -> list[TexturedPlane]:
    """Each marker of the target as a white plate with ``quiet_bits`` of white around the
    black square, seen from +z."""
    bits = _dictionary(target.dictionary).markerSize + 2
    n = params.texels_per_bit
    planes = []
    for m in target.markers:
        tex = _marker_texture(target.dictionary, m.id, n, quiet_bits, (params.black, params.white))
        t = m.size / (bits * n)
        half = tex.shape[0] * t / 2
        A = np.array([[1 / t, 0, half / t - 0.5], [0, -1 / t, half / t - 0.5], [0, 0, 1]])
        T = np.asarray(T_rig_target, dtype=np.float64) @ m.T_target_marker
        planes.append(TexturedPlane(tex, T, A, front=1))
    return planes


# --- rendering --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Placed:
    plane: TexturedPlane
    M: Array  # normalised (x, y, 1) → texel (mx·w, my·w, w), w = 1/depth
    box: tuple[int, int, int, int]  # u0, v0, u1, v1 (exclusive), inside the image


def _place(
    camera: Camera, plane: TexturedPlane, params: RenderParams, margin: int
) -> _Placed | None:
    """The plate's homography and pixel box in this camera, or None when it is not seen
    (behind, from its back, beyond the incidence limit or outside the image)."""
    T = np.linalg.inv(camera.T_rig_cam) @ plane.T_rig_plane
    R, t = T[:3, :3], T[:3, 3]
    rim = plane.outline()
    centre = rim.mean(axis=0)
    cam_in_plane = -R.T @ t
    to_cam = cam_in_plane - np.array([centre[0], centre[1], 0.0])
    cos_inc = plane.front * to_cam[2] / np.linalg.norm(to_cam)
    if cos_inc <= np.cos(np.radians(params.max_incidence_deg)):
        return None
    pts = rim @ R[:, :2].T + t
    if np.any(pts[:, 2] <= 1e-6 * np.linalg.norm(t)):
        return None
    K = camera.K
    xd, yd = distort(pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2], camera.dist)
    u, v = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]
    u0 = max(int(np.floor(u.min())) - margin, 0)
    v0 = max(int(np.floor(v.min())) - margin, 0)
    u1 = min(int(np.ceil(u.max())) + margin + 1, camera.width)
    v1 = min(int(np.ceil(v.max())) + margin + 1, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    M = plane.texel_from_plane @ np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
    return _Placed(plane, M, (u0, v0, u1, v1))


def _lookup(texture: Array, mx: Array, my: Array) -> Array:
    """Bilinear texture values at map coordinates (cv2.remap, in strips it can take)."""
    if max(texture.shape) >= _REMAP_MAX:
        raise ValueError(f"texture {texture.shape} too large: lower texels_per_bit")
    strips = [
        cv2.remap(
            texture,
            mx[:, a : a + _REMAP_MAX],
            my[:, a : a + _REMAP_MAX],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        for a in range(0, mx.shape[1], _REMAP_MAX)
    ]
    out: Array = strips[0] if len(strips) == 1 else np.hstack(strips)
    return out


def render_clean(camera: Camera, planes: list[TexturedPlane], params: RenderParams) -> Array:
    """The sharp image (float32 grey levels): no blur, no noise, not quantised."""
    img = np.full((camera.height, camera.width), params.background, np.float32)
    margin = 2 + (psf_kernel(params.psf).shape[0] // 2 if params.psf else 0)
    placed = [p for p in (_place(camera, pl, params, margin) for pl in planes) if p]
    if not placed:
        return img
    s = params.supersample
    width = max(p.box[2] for p in placed) - min(p.box[0] for p in placed)
    rows = int(np.clip(_CHUNK_SAMPLES // (s * s * width), 1, _REMAP_MAX // s))
    for r0 in range(min(p.box[1] for p in placed), max(p.box[3] for p in placed), rows):
        r1 = min(r0 + rows, camera.height)
        active = [p for p in placed if p.box[1] < r1 and p.box[3] > r0]
        if not active:
            continue
        c0, c1 = min(p.box[0] for p in active), max(p.box[2] for p in active)
        x, y = _undistorted_samples(camera, (r0, r1), (c0, c1), s)
        value = np.full(x.shape, params.background, np.float32)
        nearest = np.zeros(x.shape, np.float32)  # 1/depth of what was drawn
        for p in active:
            a, b = (p.box[0] - c0) * s, (p.box[2] - c0) * s
            xs, ys = x[:, a:b], y[:, a:b]
            m = p.M.astype(np.float32)
            w, mx, my = (_row_times(m[k], xs, ys) for k in (2, 0, 1))
            mx /= w
            my /= w
            th, tw = p.plane.texture.shape
            seen = (w > nearest[:, a:b]) & (mx >= -0.5) & (mx <= tw - 0.5)
            seen &= (my >= -0.5) & (my <= th - 0.5)
            if not seen.any():
                continue
            tex = _lookup(p.plane.texture, mx, my)
            np.copyto(value[:, a:b], tex, where=seen)
            np.copyto(nearest[:, a:b], w, where=seen)
        img[r0:r1, c0:c1] = cv2.resize(value, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA)
    return img


def _row_times(row: Array, x: Array, y: Array) -> Array:
    """row · (x, y, 1) at every sample, in their float type, with one temporary."""
    out: Array = x * row[0]
    out += y * row[1]
    out += row[2]
    return out


def _undistorted_samples(
    camera: Camera, rows: tuple[int, int], cols: tuple[int, int], s: int
) -> tuple[Array, Array]:
    """Undistorted normalised coordinates (float32) of the s×s sub-samples of every pixel
    ``rows`` × ``cols``: solved exactly (float64) at the pixel centres
    (:func:`_centre_grid`, once per camera), linearly interpolated between them along
    the rows and the columns (``cv2.resize``'s bilinear enlargement puts its samples at
    exactly the sub-samples' offsets), in float32. The map is smooth: its curvature
    makes the interpolation err by about 1e-8 of the focal length (1e-5 px), float32 by
    at most 4e-5 px; 25 times fewer points solved than sub-samples."""
    X, Y = _centre_grid(camera)
    (r0, r1), (c0, c1) = rows, cols
    # the block and a pixel around it (the grid's row and column 0 are pixel −1), so
    # that the sub-samples of the block's edge pixels interpolate, never clamp
    size = ((c1 - c0 + 2) * s, (r1 - r0 + 2) * s)
    out = []
    for grid in (X, Y):
        fine = cv2.resize(grid[r0 : r1 + 2, c0 : c1 + 2], size, interpolation=cv2.INTER_LINEAR)
        out.append(np.ascontiguousarray(fine[s:-s, s:-s]))
    return out[0], out[1]


def _centre_grid(camera: Camera) -> tuple[Array, Array]:
    """Undistorted normalised coordinates (solved in float64, kept in float32) of every
    pixel centre of the camera and of a pixel around the image (row and column 0 are
    pixel −1): solved once per camera (a few MB; the last 8 cameras are kept)."""
    K = np.asarray(camera.K, dtype=np.float64)
    dist = np.asarray(camera.dist, dtype=np.float64)
    return _solved_grid(camera.width, camera.height, K.tobytes(), dist.tobytes())


@lru_cache(maxsize=8)
def _solved_grid(width: int, height: int, K_bytes: bytes, dist_bytes: bytes) -> tuple[Array, Array]:
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_bytes, dtype=np.float64)
    cc = np.arange(-1, width + 1, dtype=np.float64)
    rr = np.arange(-1, height + 1, dtype=np.float64)
    X, Y = undistort(((cc - K[0, 2]) / K[0, 0])[None, :], ((rr - K[1, 2]) / K[1, 1])[:, None],
                     dist)  # fmt: skip
    # float32, as the sub-samples are: its rounding is 3e-8 of the focal length
    return X.astype(np.float32), Y.astype(np.float32)


@lru_cache(maxsize=16)
def psf_kernel(psf: Psf | None) -> Array:
    """The blur kernel (odd square, sums to 1): the disk ⊛ Gaussian integrated over each
    pixel cell (16×16 points a cell)."""
    if psf is None:
        return np.ones((1, 1), np.float32)
    fine = 16
    half = int(np.ceil(psf.disk_radius_px + 4.0 * psf.gaussian_sigma_px + 0.5))
    n = 2 * half + 1
    c = (np.arange(n * fine) + 0.5) / fine - n / 2
    X, Y = np.meshgrid(c, c)
    disk = np.less_equal(X * X + Y * Y, psf.disk_radius_px**2).astype(np.float64)
    if not disk.any():  # no defocus: a point
        mid = n * fine // 2
        disk[mid - 1 : mid + 1, mid - 1 : mid + 1] = 0.25
    if psf.gaussian_sigma_px > 0:
        disk = cv2.GaussianBlur(  # type: ignore[assignment]
            disk, (0, 0), psf.gaussian_sigma_px * fine, borderType=cv2.BORDER_CONSTANT
        )
    k = disk.reshape(n, fine, n, fine).sum(axis=(1, 3))
    out: Array = (k / k.sum()).astype(np.float32)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=8)
def _prnu(width: int, height: int, name: str, amount: float) -> Array:
    """A camera's fixed relative gain pattern (seeded from its name and size), drawn once
    per camera as a sensor's is made once."""
    seed = [width, height, *name.encode()]
    g = np.random.default_rng(seed).standard_normal((height, width), np.float32)
    out: Array = 1.0 + np.float32(amount) * g
    out.setflags(write=False)
    return out


def render(
    camera: Camera,
    planes: list[TexturedPlane],
    params: RenderParams,
    rng: np.random.Generator | None = None,
) -> Array:
    """The camera's 8-bit image of the plates: sharp render, blur, PRNU and noise (drawn
    from ``rng``; a fresh unseeded one when None), quantised with saturation."""
    img = render_clean(camera, planes, params)
    if params.psf is not None:
        img = cv2.filter2D(img, -1, psf_kernel(params.psf), borderType=cv2.BORDER_REPLICATE)
    sensor = params.sensor
    if sensor is not None:
        if sensor.prnu > 0:
            img *= _prnu(camera.width, camera.height, camera.name, sensor.prnu)
        if sensor.noise_grey > 0:
            gen = rng if rng is not None else np.random.default_rng()
            img += gaussian_noise(img.shape, gen, sensor.noise_grey)
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)
    out: Array = img.astype(np.uint8)
    return out


def render_board(
    rig: Rig, board: Board, T_rig_board: Array, params: RenderParams, seed: int = 0
) -> dict[str, Array]:
    """Every camera's image of the board at ``T_rig_board`` (noise from ``seed``)."""
    planes = [board_plane(board, T_rig_board, params)]
    return {
        cam.name: render(cam, planes, params, np.random.default_rng([seed, k]))
        for k, cam in enumerate(rig.cameras)
    }


def render_target(
    rig: Rig, target: Target, T_rig_target: Array, params: RenderParams, seed: int = 0
) -> dict[str, Array]:
    """Every camera's image of the target at ``T_rig_target`` (noise from ``seed``)."""
    planes = marker_planes(target, T_rig_target, params)
    return {
        cam.name: render(cam, planes, params, np.random.default_rng([seed, k]))
        for k, cam in enumerate(rig.cameras)
    }


if __name__ == "__main__":
    from cellcal.mocks.rig.texture_scenes import main

    main()
