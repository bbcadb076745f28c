"""Cameras, marker targets and calibration boards of the photogrammetry rig.

Pure numerics: numpy in, frozen dataclasses out. OpenCV conventions throughout: pinhole
camera, x right, y down, z along the optical axis; pixel centres at integer coordinates;
distortion coefficients as OpenCV orders them (``k1, k2, p1, p2, k3[, k4, k5, k6[, s1..s4
[, τx, τy]]]``). Frames follow cellcal's convention: ``T_a_b`` maps coordinates in frame b
into frame a. Lengths are millimetres, pixels px.

Each dataclass checks itself on construction and raises :class:`InputError` as
``KEY: what`` (the key as the contract's files name it), so a reader can prefix the file
and the table (``rig.toml: camera[2].K: …``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from cellcal.calib.geometry import Array
from cellcal.errors import InputError

#: Distortion vector lengths OpenCV accepts (the contract: 5, 8, 12 or 14).
DIST_LENGTHS = (5, 8, 12, 14)
#: Tolerance of a rigid transform's rotation: ``|RᵀR − I|`` and ``|det R − 1|``.
RIGID_TOL = 1e-6
#: Iterations of the point undistortion (OpenCV's default of 5 is not metrology).
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def _array(value: object, shape: tuple[int, ...], key: str) -> Array:
    """A read-only float copy of ``value`` of the given shape, finite."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{key}: expected numbers") from None
    if a.shape != shape:
        want = "×".join(map(str, shape))
        got = "×".join(map(str, a.shape)) or "a scalar"
        raise InputError(f"{key}: expected {want} numbers, got {got}")
    if not np.isfinite(a).all():
        raise InputError(f"{key}: not finite")
    a.setflags(write=False)
    return a


def _positive(value: object, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise InputError(f"{key}: expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x) or x <= 0.0:
        raise InputError(f"{key}: must be positive and finite, got {x:g}")
    return x


def _positive_int(value: object, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
        raise InputError(f"{key}: must be a positive integer, got {value!r}")
    return int(value)


def _name(value: object, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{key}: must be a non-empty string")
    return value


def rigid(value: object, key: str) -> Array:
    """A 4×4 rigid transform: orthonormal rotation (det +1) within :data:`RIGID_TOL`,
    last row 0 0 0 1."""
    T = _array(value, (4, 4), key)
    R = T[:3, :3]
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{key}: not a rigid transform (last row must be 0 0 0 1)")
    if (
        np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL
        or abs(float(np.linalg.det(R)) - 1.0) > RIGID_TOL
    ):
        raise InputError(
            f"{key}: not a rigid transform (rotation not orthonormal with det +1 "
            f"within {RIGID_TOL:g})"
        )
    return T


def intrinsics(value: object, key: str) -> Array:
    """A 3×3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, fx and fy > 0."""
    K = _array(value, (3, 3), key)
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise InputError(f"{key}: must be upper-triangular with last row 0 0 1")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise InputError(f"{key}: focal lengths K[0][0] and K[1][1] must be positive")
    if K[0, 1] != 0.0:
        raise InputError(f"{key}: skew K[0][1] must be 0 (OpenCV's projection ignores it)")
    return K


def dictionary_size(name: object, key: str = "dictionary") -> int:
    """The number of markers of a cv2.aruco predefined dictionary (``DICT_4X4_50``…)."""
    value = getattr(cv2.aruco, name, None) if isinstance(name, str) else None
    if not isinstance(name, str) or not name.startswith("DICT_") or not isinstance(value, int):
        raise InputError(f"{key}: {name!r} is not a cv2.aruco predefined dictionary")
    return int(cv2.aruco.getPredefinedDictionary(value).bytesList.shape[0])


def _unique(values: list[object], what: str, key: str) -> None:
    seen: dict[object, int] = {}
    for k, v in enumerate(values, start=1):
        if v in seen:
            raise InputError(f"{what}[{k}].{key}: {v!r} repeats {what}[{seen[v]}]")
        seen[v] = k


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera: intrinsics, distortion and its pose in the rig frame."""

    name: str
    width: int
    height: int
    K: Array
    dist: Array
    T_rig_cam: Array
    reprojection_rms_px: float | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "name", _name(self.name, "name"))
        set_(self, "width", _positive_int(self.width, "width"))
        set_(self, "height", _positive_int(self.height, "height"))
        set_(self, "K", intrinsics(self.K, "K"))
        try:
            n = np.size(self.dist) if np.ndim(self.dist) == 1 else -1
        except ValueError:  # a ragged list
            n = -1
        if n not in DIST_LENGTHS:
            raise InputError("dist: expected 5, 8, 12 or 14 coefficients (OpenCV's order)")
        set_(self, "dist", _array(self.dist, (n,), "dist"))
        set_(self, "T_rig_cam", rigid(self.T_rig_cam, "T_rig_cam"))
        rms = self.reprojection_rms_px
        if rms is not None:
            if isinstance(rms, bool) or not isinstance(rms, int | float | np.number):
                raise InputError(f"reprojection_rms_px: expected a number, got {rms!r}")
            if not math.isfinite(rms) or rms < 0.0:
                raise InputError("reprojection_rms_px: must be finite and not negative")
            set_(self, "reprojection_rms_px", float(rms))

    def project(self, points_rig: Array) -> Array:
        """Pixel coordinates (n, 2) of points (n, 3) given in the rig frame (mm).
        Points behind the camera are projected too; the caller decides what is seen."""
        p = np.asarray(points_rig, dtype=np.float64).reshape(-1, 3)
        rvec, tvec = self._rig_in_camera
        px, _ = cv2.projectPoints(p, rvec, tvec, self.K, self.dist)
        out: Array = px.reshape(-1, 2).astype(np.float64)
        return out

    @cached_property
    def _rig_in_camera(self) -> tuple[Array, Array]:
        """The rig frame in the camera's, as OpenCV's (rvec, tvec)."""
        T_cam_rig = np.linalg.inv(self.T_rig_cam)
        rvec, _ = cv2.Rodrigues(T_cam_rig[:3, :3])
        tvec: Array = np.array(T_cam_rig[:3, 3], dtype=np.float64)
        return np.asarray(rvec, dtype=np.float64), tvec

    def normalised(self, pixels: Array) -> Array:
        """Undistorted normalised coordinates (x/z, y/z) (n, 2) of pixel positions (n, 2)."""
        uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(uv, self.K, self.dist, criteria=_UNDISTORT)
        out: Array = xy.reshape(-1, 2).astype(np.float64)
        return out


@dataclass(frozen=True, eq=False)
class Rig:
    """The cameras of one rig; names unique."""

    name: str
    cameras: tuple[Camera, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", _name(self.name, "name"))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if not self.cameras:
            raise InputError("camera: at least one [[camera]] table is needed")
        _unique([c.name for c in self.cameras], "camera", "name")

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise InputError(f"no camera {name!r} in rig {self.name!r}")


#: A marker's corners in its own frame, in the detector's order (TL, TR, BR, BL).
_UNIT_CORNERS = np.array([[-0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0.5, -0.5, 0.0], [-0.5, -0.5, 0.0]])


@dataclass(frozen=True, eq=False)
class Marker:
    """One square marker: ``size`` the edge of the black square; its frame has the origin
    at the square's centre, x right, y up, z out of the face."""

    id: int
    size: float
    T_target_marker: Array

    def __post_init__(self) -> None:
        if isinstance(self.id, bool) or not isinstance(self.id, int | np.integer) or self.id < 0:
            raise InputError(f"id: must be a non-negative integer, got {self.id!r}")
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "size", _positive(self.size, "size"))
        object.__setattr__(self, "T_target_marker", rigid(self.T_target_marker, "T_target_marker"))

    def corners(self) -> Array:
        """The 4 corners (4, 3) in the target frame: top-left, top-right, bottom-right,
        bottom-left, as the detector returns them."""
        local = _UNIT_CORNERS * self.size
        out: Array = local @ self.T_target_marker[:3, :3].T + self.T_target_marker[:3, 3]
        return out


@dataclass(frozen=True, eq=False)
class Target:
    """A marker fixture: its markers and the point reported as the measurement."""

    name: str
    dictionary: str
    reference: Array
    markers: tuple[Marker, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", _name(self.name, "name"))
        size = dictionary_size(self.dictionary)
        object.__setattr__(self, "reference", _array(self.reference, (3,), "reference"))
        object.__setattr__(self, "markers", tuple(self.markers))
        if not self.markers:
            raise InputError("marker: at least one [[marker]] table is needed")
        for k, m in enumerate(self.markers, start=1):
            if m.id >= size:
                raise InputError(
                    f"marker[{k}].id: {m.id} is not in {self.dictionary} (ids 0..{size - 1})"
                )
        _unique([m.id for m in self.markers], "marker", "id")


@dataclass(frozen=True, eq=False)
class Board:
    """A ChArUco calibration board: ``squares`` (nx, ny), square and marker edges (mm);
    ``legacy`` for boards printed before OpenCV 4.6."""

    dictionary: str
    squares: tuple[int, int]
    square: float
    marker: float
    legacy: bool = False

    def __post_init__(self) -> None:
        size = dictionary_size(self.dictionary)
        sq = tuple(self.squares)
        if len(sq) != 2 or any(
            isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 2 for n in sq
        ):
            raise InputError("squares: expected [nx, ny], integers of at least 2")
        nx, ny = int(sq[0]), int(sq[1])
        object.__setattr__(self, "squares", (nx, ny))
        if nx * ny // 2 > size:
            raise InputError(
                f"squares: a {nx}×{ny} board needs {nx * ny // 2} markers, "
                f"{self.dictionary} has {size}"
            )
        object.__setattr__(self, "square", _positive(self.square, "square"))
        object.__setattr__(self, "marker", _positive(self.marker, "marker"))
        if self.marker >= self.square:
            raise InputError(
                f"marker: {self.marker:g} must be smaller than square ({self.square:g})"
            )
        if not isinstance(self.legacy, bool | np.bool_):
            raise InputError(f"legacy: expected true or false, got {self.legacy!r}")
        object.__setattr__(self, "legacy", bool(self.legacy))

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board (OpenCV ≥ 4.7 API)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard(self.squares, self.square, self.marker, dictionary)
        board.setLegacyPattern(self.legacy)
        return board
