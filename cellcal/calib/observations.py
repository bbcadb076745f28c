"""What a fit reads, checked: joint readings, positions, their targets and sessions, the
measured orientations of a 6-DOF sensor, their weights, and the closed-form start.

``cellcal.calib.identification`` fits; this module holds the data side of the fit so
that both stay readable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_model import (
    Groups,
    Index,
    ParameterSpec,
    State,
    jacobian,
    orientation_residuals,
    predict,
    predict_orientation,
)
from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.registration import fit_rigid
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import DegenerateGeometryError, InputError

#: The starting weight of an orientation residual against a position residual (mm/rad:
#: 0.02 mm against 0.2 mrad); re-balanced from the residuals of the fit.
ORIENTATION_WEIGHT_START = 100.0


def check_measurements(
    model: RobotModel, q: Array, measured: Array, sigma: Array | None
) -> tuple[Array, Array, Array | None]:
    """Shapes, finiteness and joint limits; returns float64 copies."""
    q = np.asarray(q, dtype=np.float64)
    m = np.asarray(measured, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != model.dof:
        raise InputError(f"joint readings: expected N×{model.dof}, got shape {q.shape}")
    if m.shape != (len(q), 3):
        raise InputError(f"measurements: expected {len(q)}×3 positions, got shape {m.shape}")
    for name, arr in (("joint readings", q), ("measurements", m)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if len(bad):
            raise InputError(f"{name}: row {int(bad[0]) + 1} is not finite")
    lo, hi = model.limits
    outside = (q < lo - 1e-9) | (q > hi + 1e-9)
    if outside.any():
        r, j = (int(v) for v in np.argwhere(outside)[0])
        raise InputError(
            f"row {r + 1}: joint {j + 1} reads {math.degrees(q[r, j]):.3f}°, outside the "
            f"model's limits [{math.degrees(lo[j]):.1f}°, {math.degrees(hi[j]):.1f}°]"
        )
    s = None
    if sigma is not None:
        s = np.asarray(sigma, dtype=np.float64)
        if s.shape != m.shape or not np.isfinite(s).all() or (s <= 0).any():
            raise InputError("sx, sy, sz: must be positive, finite, one triple per row")
    return q, m, s


#: Points whose RMS distance from their best-fit line is below this fraction of their
#: RMS spread along it lie "on a line": they cannot fix a sensor frame's rotation about
#: that line (a robot moved along a straight path leaves tenths of a millimetre across
#: it, its own errors, which such a fit would read as that rotation).
LINE_RATIO = 0.01
#: Measurements that span less than this (mm) in every direction stay put: the target
#: does not follow the robot (an acceptance check, exit 3), which is said before they
#: are called degenerate geometry.
STILL_MM = 1.0


@dataclass(frozen=True)
class LineLayout:
    """Points that lie on a line: their RMS distance from it and their extent along it
    (mm)."""

    n: int
    across_rms_mm: float
    along_mm: float

    def reason(self) -> str:
        return (
            f"its {self.n} points lie within {self.across_rms_mm:.3g} mm (RMS) of one line "
            f"{self.along_mm:.0f} mm long: they cannot fix the sensor frame's rotation about "
            "that line"
        )


def on_a_line(points: Array) -> LineLayout | None:
    """The layout of ``points`` (n×3, mm) when they lie on a line (or at one point),
    else None."""
    c = points - points.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False) / np.sqrt(max(len(points), 1))
    across = float(np.hypot(sv[1], sv[2]))
    if not across > LINE_RATIO * sv[0]:
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        along = c @ vt[0]
        return LineLayout(len(points), across, float(np.ptp(along)))
    return None


def check_sessions(measured: Array, groups: Groups) -> None:
    """Each session's measurements must determine its sensor frame: at least 3, not
    on a line or at one point."""
    for s, name in enumerate(groups.sessions):
        m_s = measured[groups.session == s]
        several = len(groups.sessions) > 1
        if several and len(m_s) < 3:
            raise DegenerateGeometryError(
                f"session {name!r} has {len(m_s)} measurement(s); each sensor set-up "
                "needs at least 3 (spread over a volume)"
            )
        line = on_a_line(m_s)
        if line is not None:
            who = f"session {name!r}" if several else "the measurements"
            raise DegenerateGeometryError(
                f"{who}: {line.reason()}; measure poses off the line (spread over a "
                "plane or a volume)"
            )


def register_sessions(p_base: Array, measured: Array, groups: Groups) -> tuple[Array, Array]:
    """Each session's sensor frame (Rs S×3×3, ts S×3) registering the base-frame
    positions ``p_base`` (N×3) to the measurements (SVD)."""
    S = len(groups.sessions)
    Rs, ts = np.empty((S, 3, 3)), np.empty((S, 3))
    for s in range(S):
        rows = groups.session == s
        fit = fit_rigid(p_base[rows], measured[rows])
        Rs[s], ts[s] = fit.R, fit.t
    return Rs, ts


def initial_state(
    model: RobotModel,
    q: Array,
    measured: Array,
    groups: Groups | None = None,
    orientations: Array | None = None,
) -> State:
    """Closed-form start: register the nominal positions to the measurements of each
    session (SVD), solve the target offsets and the translations linearly, and register
    once more; with orientations, each target's orientation on the flange as the mean of
    what the measurements imply."""
    g = groups if groups is not None else Groups.single(len(q))
    S, T = len(g.sessions), len(g.targets)
    check_sessions(measured, g)
    k = target_kinematics(model, q, model.target_offset, jacobian=False)
    Rs, _ = register_sessions(k.p, measured, g)
    # measured − R_s·o_flange = R_s·R_flange·tool_t + t_s: linear in (tools, ts).
    N = len(q)
    Rp = Rs[g.session]
    A = np.zeros((N, 3, 3 * T + 3 * S))
    RR = np.einsum("nij,njk->nik", Rp, k.R_flange)
    rows = np.arange(N)
    for c in range(3):
        A[rows, :, 3 * g.target + c] = RR[:, :, c]
        A[rows, c, 3 * T + 3 * g.session + c] = 1.0
    b = measured - np.einsum("nij,nj->ni", Rp, k.p - k.R_flange @ model.target_offset)
    sol, _, rank, _ = np.linalg.lstsq(A.reshape(-1, A.shape[2]), b.reshape(-1), rcond=1e-9)
    target_offsets = (
        sol[: 3 * T].reshape(T, 3) if rank == A.shape[2] else np.tile(model.target_offset, (T, 1))
    )
    k = target_kinematics(model, q, target_offsets[g.target], jacobian=False)
    Rs, ts = register_sessions(k.p, measured, g)
    pivots = np.stack([measured[g.session == s].mean(axis=0) for s in range(S)])
    target_rotations = None
    if orientations is not None:
        target_rotations = np.empty((T, 3, 3))
        implied = np.swapaxes(Rs[g.session] @ k.R_flange, 1, 2) @ orientations
        for t in range(T):
            U, _, Vt = np.linalg.svd(implied[g.target == t].sum(axis=0))
            target_rotations[t] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return State(model, target_offsets, Rs, ts, pivots, target_rotations)


def weights(sigma: Array | None, n: int, orientation: bool = False) -> Array:
    """Per measurement: 1/σ of x, y, z (and of the three orientation components)."""
    w = np.ones((n, 3)) if sigma is None else 1.0 / sigma
    if orientation:
        w = np.hstack([w, np.full((n, 3), ORIENTATION_WEIGHT_START * float(np.mean(w)))])
    return w


@dataclass(frozen=True)
class Data:
    """What a fit reads: joint readings (rad), positions (mm), their groups, and the
    measured orientations (N×3×3) of a 6-DOF sensor or None."""

    q: Array
    measured: Array
    groups: Groups
    orientations: Array | None = None
    #: time, temperature and payload per measurement, for error terms (None: not given)
    conditions: Conditions | None = None

    def residuals(self, state: State) -> Array:
        """Measured − predicted: N×3 (mm), or N×6 with the orientations' (rad)."""
        r = self.measured - predict(state, self.q, self.groups, self.conditions)
        if self.orientations is None:
            return r
        o = orientation_residuals(
            self.orientations, predict_orientation(state, self.q, self.groups)
        )
        out: Array = np.hstack([r, o])
        return out

    def jacobian(self, state: State, specs: tuple[ParameterSpec, ...]) -> Array:
        return self.jacobian_and_positions(state, specs)[1]

    def jacobian_and_positions(
        self, state: State, specs: tuple[ParameterSpec, ...]
    ) -> tuple[Array, Array]:
        """Predicted positions (N×3) and the Jacobian (N×3×P or N×6×P), from one pass."""
        return jacobian(
            state, self.q, specs, self.groups, self.orientations is not None, self.conditions
        )

    def subset(self, rows: Index) -> Data:
        o = None if self.orientations is None else self.orientations[rows]
        c = None if self.conditions is None else self.conditions.subset(rows)
        return Data(self.q[rows], self.measured[rows], self.groups.subset(rows), o, c)


def check_orientations(orientations: Array | None, n: int) -> Array | None:
    """Measured orientations: N rotation matrices (3×3), or None."""
    if orientations is None:
        return None
    o = np.asarray(orientations, dtype=np.float64)
    if o.shape != (n, 3, 3) or not np.isfinite(o).all():
        raise InputError(f"orientations: expected {n} rotation matrices (3×3)")
    err = np.abs(o @ np.swapaxes(o, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-6) | (np.linalg.det(o) < 0))
    if len(bad):
        raise InputError(f"orientation of row {int(bad[0]) + 1} is not a rotation")
    return o


def balance(w: Array, r: Array) -> Array:
    """Orientation weights re-scaled so that weighted position and orientation residuals
    have the same spread (variance components estimated from the fit)."""
    sp = float(np.sqrt(np.mean((r[:, :3] * w[:, :3]) ** 2)))
    so = float(np.sqrt(np.mean((r[:, 3:] * w[:, 3:]) ** 2)))
    out = w.copy()
    if sp > 0 and so > 0:
        out[:, 3:] *= sp / so
    return out
