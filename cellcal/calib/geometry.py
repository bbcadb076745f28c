"""Small rigid-body helpers: skew matrices, SO(3) exponential, homogeneous transforms.

Frames follow cellcal's convention: ``T_a_b`` maps coordinates in frame b into frame a,
``p_a = T_a_b @ p_b``. Lengths are millimetres, angles radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.rotations import rotvec_from_matrix

Array = NDArray[np.float64]


def skew(v: Array) -> Array:
    """The 3×3 matrix ``[v]×`` with ``[v]× @ w == cross(v, w)``."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w`` (axis times angle, radians)."""
    theta2 = float(w @ w)
    K = skew(w)
    if theta2 < 1e-16:
        # Second-order Taylor expansion; exact to machine precision at this size.
        small: Array = np.eye(3) + K + 0.5 * (K @ K)
        return small
    theta = np.sqrt(theta2)
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta2
    out: Array = np.eye(3) + a * K + b * (K @ K)
    return out


def so3_log(R: Array) -> Array:
    """Rotation vector of the rotation matrix ``R`` (inverse of :func:`so3_exp`)."""
    return rotvec_from_matrix(R)


def rotation_angle(R: Array) -> float:
    """Angle of the rotation ``R`` in radians, in [0, π], computed with atan2."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    s = 0.5 * float(np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]))
    return float(np.arctan2(s, c))


def homogeneous(R: Array, t: Array, scale: float = 1.0) -> Array:
    """The 4×4 matrix mapping ``p`` to ``scale * R @ p + t``."""
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = t
    return T


def apply(T: Array, points: Array) -> Array:
    """Apply the homogeneous transform ``T`` to an (n, 3) array of points."""
    out: Array = points @ T[:3, :3].T + T[:3, 3]
    return out


def invert(T: Array) -> Array:
    """Inverse of a rigid (or similarity) homogeneous transform."""
    A = T[:3, :3]
    Ai = np.linalg.inv(A)
    out = np.eye(4)
    out[:3, :3] = Ai
    out[:3, 3] = -Ai @ T[:3, 3]
    return out


def wrap_deg(angle: float) -> float:
    """An angle in degrees wrapped to (−180°, 180°]."""
    out = -((-angle + 180.0) % 360.0 - 180.0)
    return out + 0.0


def wrap_rad(angle: float) -> float:
    """An angle in radians wrapped to (−π, π]."""
    out = -((-angle + np.pi) % (2 * np.pi) - np.pi)
    return float(out) + 0.0
