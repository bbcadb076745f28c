"""Conversions between rotation matrices, rotation vectors, unit quaternions and Euler
angles, batched over leading axes, in numpy alone.

Why not ``scipy.spatial.transform.Rotation``: importing it loads all of scipy.spatial
(k-d trees, Qhull, scipy.sparse, scipy.special), about 0.4 s of CPU at the start of
every process that turns one matrix into a rotation vector — every twin, every service,
every command. The formulas are the textbook ones scipy uses too (quaternion from a
matrix by the largest of its four candidates, rotation vector through the half-angle
with a series near zero); tests/calib/test_rotations.py checks each against scipy on
random rotations and at the edges (identity, half turns, gimbal lock).

Quaternions are (w, x, y, z), w first, as cellcal's files hold them. Angles are radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Below this angle (rad) the rotation-vector formulas use their Taylor series.
SMALL_ANGLE = 1e-3


def _skew(w: Array) -> Array:
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = np.zeros_like(x)
    K: Array = np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(*w.shape[:-1], 3, 3)
    return K


def matrix_from_rotvec(w: Array) -> Array:
    """Rotation matrices (…×3×3) of rotation vectors (…×3: axis times angle)."""
    w = np.asarray(w, dtype=np.float64)
    t2 = np.sum(w * w, axis=-1)
    t = np.sqrt(t2)
    small = t < SMALL_ANGLE
    ts = np.where(small, 1.0, t)
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(ts)) / (ts * ts))
    K = _skew(w)
    R: Array = np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)
    return R


def quaternion_from_matrix(R: Array) -> Array:
    """Unit quaternions (…×4, w first, w ≥ 0) of rotation matrices (…×3×3).

    Each is built from whichever of w, x, y, z is largest, where the formula is best
    conditioned; a matrix a little off orthonormal gives the normalised result."""
    R = np.asarray(R, dtype=np.float64)
    d0, d1, d2 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = d0 + d1 + d2
    c = np.stack(
        [
            np.stack([1.0 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                      R[..., 1, 0] - R[..., 0, 1]], axis=-1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1.0 + d0 - d1 - d2,
                      R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], axis=-1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0],
                      1.0 - d0 + d1 - d2, R[..., 1, 2] + R[..., 2, 1]], axis=-1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0],
                      R[..., 1, 2] + R[..., 2, 1], 1.0 - d0 - d1 + d2], axis=-1),
        ],
        axis=-2,
    )  # fmt: skip
    pick = np.argmax(np.stack([tr, d0, d1, d2], axis=-1), axis=-1)
    q = np.take_along_axis(c, pick[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    out: Array = np.where(q[..., :1] < 0.0, -q, q)
    return out


def matrix_from_quaternion(q: Array) -> Array:
    """Rotation matrices (…×3×3) of quaternions (…×4, w first; normalised here)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R: Array = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip
    return R


def rotvec_from_matrix(R: Array) -> Array:
    """Rotation vectors (…×3, angle in [0, π]) of rotation matrices (…×3×3)."""
    q = quaternion_from_matrix(R)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(n, q[..., 0])
    small = angle < SMALL_ANGLE
    a2 = angle * angle
    scale = np.where(
        small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, angle / np.where(small, 1.0, n)
    )
    out: Array = scale[..., None] * v
    return out


def matrix_from_euler_xyz(angles: Array) -> Array:
    """Rotation matrices (…×3×3) of rotations about the fixed x, then y, then z axes
    (…×3: a, b, c), that is ``Rz(c) @ Ry(b) @ Rx(a)``."""
    angles = np.asarray(angles, dtype=np.float64)
    ca, cb, cc = np.cos(angles[..., 0]), np.cos(angles[..., 1]), np.cos(angles[..., 2])
    sa, sb, sc = np.sin(angles[..., 0]), np.sin(angles[..., 1]), np.sin(angles[..., 2])
    R: Array = np.stack(
        [
            cb * cc, sa * sb * cc - ca * sc, ca * sb * cc + sa * sc,
            cb * sc, sa * sb * sc + ca * cc, ca * sb * sc - sa * cc,
            -sb, sa * cb, ca * cb,
        ],
        axis=-1,
    ).reshape(*angles.shape[:-1], 3, 3)  # fmt: skip
    return R


def euler_zyx_from_matrix(R: Array) -> Array:
    """Z-Y-X Euler angles (…×3: A about z, B about the new y, C about the newest x) with
    ``R = Rz(A) @ Ry(B) @ Rx(C)``; B in [−π/2, π/2]. At B = ±π/2 only A ∓ C is defined:
    C is then 0."""
    R = np.asarray(R, dtype=np.float64)
    cb = np.hypot(R[..., 0, 0], R[..., 1, 0])
    B = np.arctan2(-R[..., 2, 0], cb)
    locked = cb < 1e-9
    A = np.where(
        locked,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    C = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    out: Array = np.stack([A, B, C], axis=-1)
    return out


def nearest_rotation(M: Array) -> Array:
    """The rotation matrix nearest (Frobenius) to the 3×3 matrix ``M``."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    d = np.sign(np.linalg.det(U @ Vt))
    out: Array = (U * np.array([1.0, 1.0, d])) @ Vt
    return out
