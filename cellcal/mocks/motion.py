"""The one motion model of the simulated controllers: a synchronised point-to-point move.

Every joint starts and stops together; the path is the straight line from ``q0`` to
``q1`` in joint space, and the progress along it follows a trapezoidal profile (constant
acceleration ``a``, cruise at ``v``, constant deceleration) over a distance ``distance``
in whatever unit the controller times its moves by: the leading joint's travel for a
joint move, the tool's translation for a linear one. ``a = inf`` gives a constant-speed
move (the Modbus twin's), a finite ``a`` a triangular profile when the move is too short
to reach ``v`` (UR's controller).

Units are the caller's: the UR twin works in rad, rad/s and rad/s² (or m, m/s, m/s²),
the Modbus twin in degrees. Time is the controller's own, in seconds since the move
started; each twin decides how it relates to wall time (its time scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cellcal.calib.geometry import Array

MIN_RATE = 1e-3  # the lowest speed and acceleration a move is planned with


@dataclass(frozen=True)
class JointMove:
    """q(t) = q0 + (q1 − q0)·s(t)/distance, s(t) trapezoidal; see the module docstring."""

    q0: Array
    q1: Array
    v: float
    a: float = math.inf
    distance: float | None = None  # default: the leading joint's travel
    duration: float = field(init=False)
    _t_acc: float = field(init=False, repr=False)
    _v_peak: float = field(init=False, repr=False)
    _dist: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        q0 = np.asarray(self.q0, dtype=np.float64)
        q1 = np.asarray(self.q1, dtype=np.float64)
        if q0.shape != q1.shape:
            raise ValueError(f"q0 and q1 differ in shape: {q0.shape} vs {q1.shape}")
        travel = float(np.max(np.abs(q1 - q0))) if q0.size else 0.0
        dist = travel if self.distance is None else float(self.distance)
        v, a = max(float(self.v), MIN_RATE), max(float(self.a), MIN_RATE)
        if dist <= 0.0:
            t_acc, v_peak, duration = 0.0, 0.0, 0.0
        elif math.isinf(a):
            t_acc, v_peak, duration = 0.0, v, dist / v
        elif v * v / a >= dist:  # triangular: v is never reached
            t_acc = math.sqrt(dist / a)
            v_peak, duration = a * t_acc, 2.0 * t_acc
        else:
            t_acc, v_peak = v / a, v
            duration = 2.0 * t_acc + (dist - v * t_acc) / v
        for name, value in (
            ("q0", q0),
            ("q1", q1),
            ("v", v),
            ("a", a),
            ("duration", duration),
            ("_t_acc", t_acc),
            ("_v_peak", v_peak),
            ("_dist", dist),
        ):
            object.__setattr__(self, name, value)

    def progress(self, t: float) -> tuple[float, float]:
        """Fraction of the path covered at ``t`` and its rate (1/s)."""
        D, T, ta, vp = self._dist, self.duration, self._t_acc, self._v_peak
        if D <= 0.0 or t >= T:
            return 1.0, 0.0
        if t <= 0.0:
            return 0.0, 0.0
        if t < ta:
            s, sd = 0.5 * self.a * t * t, self.a * t
        elif t <= T - ta:
            s, sd = 0.5 * vp * ta + vp * (t - ta), vp
        else:
            r = T - t
            s, sd = D - 0.5 * self.a * r * r, self.a * r
        return s / D, sd / D

    def at(self, t: float) -> tuple[Array, Array]:
        """Joint positions and velocities at ``t`` seconds into the move."""
        f, fd = self.progress(t)
        step = self.q1 - self.q0
        if f >= 1.0:
            return self.q1.copy(), np.zeros_like(step)
        q: Array = self.q0 + step * f
        qd: Array = step * fd
        return q, qd

    def done(self, t: float) -> bool:
        return t >= self.duration
