"""The calibration data files of the public contract, read at the edge.

Measurements: ``q1..qn,x,y,z`` — joint readings in degrees as the controller reports
them, target position in mm in the sensor frame — with optional columns ``name``,
``sx,sy,sz`` (1σ, mm), ``target`` (which target, when several are measured: each gets
its own offset), ``session`` (which sensor set-up: each gets its own frame) and
``ori_w,ori_x,ori_y,ori_z`` (the target's orientation in the sensor frame, a unit
quaternion, from a 6-DOF sensor), and, for error terms beyond geometry, ``time_s``
(seconds since the campaign's start), ``temperature_c`` and ``payload_kg``. Joints:
``q1..qn`` (deg), with optional ``target`` and ``session``. Angles become radians here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.calib.error_model import Groups
from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.rotations import matrix_from_quaternion
from cellcal.errors import FileFormatError
from cellcal.files.csvtable import Table, read_table

#: More rows than this are refused: the fit's Jacobian would need gigabytes.
MAX_ROWS = 100_000


@dataclass(frozen=True)
class Measurements:
    """Rows of a measurement file: ``q`` (N×n, rad), ``xyz`` (N×3, mm), ``sigma`` (N×3 mm
    or None), ``names`` (the name column, or row numbers), the ``target`` and ``session``
    labels (or None) and the measured ``orientations`` (N×3×3, or None)."""

    path: str
    names: tuple[str, ...]
    q: Array
    xyz: Array
    sigma: Array | None
    targets: tuple[str, ...] | None = None
    sessions: tuple[str, ...] | None = None
    orientations: Array | None = None
    #: time, temperature and payload per row (None: none of the columns)
    conditions: Conditions | None = None

    @property
    def groups(self) -> Groups:
        return Groups.of(len(self.q), self.targets, self.sessions)


def joint_columns(dof: int) -> tuple[str, ...]:
    return tuple(f"q{i}" for i in range(1, dof + 1))


def read_joint_columns(t: Table, dof: int) -> Array:
    cols = joint_columns(dof)
    extra = [h for h in t.header if h.startswith("q") and h[1:].isdigit() and h not in cols]
    if extra:
        raise FileFormatError(
            f"{t.path}: column {extra[0]} but the robot has {dof} joints (q1..q{dof})"
        )
    q = np.array([[t.number(k, c) for c in cols] for k in range(len(t.rows))])
    out: Array = np.radians(q)
    return out


def read_measurements(path: str | Path, dof: int = 6) -> Measurements:
    """Read a measurement CSV for a robot with ``dof`` joints."""
    cols = joint_columns(dof)
    expected = ",".join(cols) + ",x,y,z"
    t = read_table(path, (*cols, "x", "y", "z"), expected)
    if len(t.rows) > MAX_ROWS:
        raise FileFormatError(
            f"{t.path}: {len(t.rows)} rows; a calibration takes at most {MAX_ROWS} "
            "(a campaign measures hundreds to a few thousand poses)"
        )
    q = read_joint_columns(t, dof)
    xyz = np.array([[t.number(k, c) for c in ("x", "y", "z")] for k in range(len(t.rows))])
    sigma = None
    if t.has("sx", "sy", "sz"):
        sigma = np.array([[t.number(k, c) for c in ("sx", "sy", "sz")] for k in range(len(t.rows))])
        bad = np.flatnonzero((sigma <= 0).any(axis=1))
        if len(bad):
            raise FileFormatError(f"{t.where(int(bad[0]))}: sx, sy, sz must be positive (1σ, mm)")
    elif any(t.has(c) for c in ("sx", "sy", "sz")):
        raise FileFormatError(f"{t.path}: give all of sx, sy, sz or none")
    if t.has("name"):
        names = tuple(r[t.column("name")] for r in t.rows)
    else:
        names = tuple(str(k + 1) for k in range(len(t.rows)))
    return Measurements(
        t.path,
        names,
        q,
        xyz,
        sigma,
        _labels(t, "target"),
        _labels(t, "session"),
        read_orientations(t),
        read_conditions(t),
    )


#: Plausible ranges of the condition columns: a value outside is a unit slip (ms for s,
#: °F or K for °C, g for kg) or a typo, refused with the row.
CONDITION_RANGES = {
    "time_s": (0.0, 366 * 86400.0, "seconds since the campaign's start, 0 or more"),
    "temperature_c": (-40.0, 80.0, "°C, between −40 and 80 (°F or K?)"),
    "payload_kg": (0.0, 5000.0, "kg, 0 or more (grams?)"),
}


def read_conditions(t: Table) -> Conditions | None:
    """The ``time_s``, ``temperature_c``, ``payload_kg`` columns, or None when absent."""
    found: dict[str, Array] = {}
    for column, (lo, hi, what) in CONDITION_RANGES.items():
        if not t.has(column):
            continue
        values = np.array([t.number(k, column) for k in range(len(t.rows))])
        bad = np.flatnonzero((values < lo) | (values > hi))
        if len(bad):
            k = int(bad[0])
            raise FileFormatError(f"{t.where(k)}: {column} {values[k]:g} is not {what}")
        found[column] = values
    return Conditions(**found) if found else None


def _labels(t: Table, column: str) -> tuple[str, ...] | None:
    """A label column (``target``, ``session``), or None when absent; empty is refused."""
    if not t.has(column):
        return None
    out = tuple(r[t.column(column)].strip() for r in t.rows)
    empty = [k for k, v in enumerate(out) if not v]
    if empty:
        raise FileFormatError(f"{t.where(empty[0])}: empty {column}")
    return out


#: A quaternion whose length is off 1 by more than this is not an orientation.
UNIT_QUATERNION_TOL = 1e-3


def read_orientations(t: Table) -> Array | None:
    """``ori_w,ori_x,ori_y,ori_z`` as rotation matrices (N×3×3), or None when absent."""
    cols = ("ori_w", "ori_x", "ori_y", "ori_z")
    if not any(t.has(c) for c in cols):
        return None
    if not t.has(*cols):
        raise FileFormatError(f"{t.path}: give all of ori_w, ori_x, ori_y, ori_z or none")
    wxyz = np.array([[t.number(k, c) for c in cols] for k in range(len(t.rows))])
    norm = np.linalg.norm(wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > UNIT_QUATERNION_TOL)
    if len(bad):
        raise FileFormatError(
            f"{t.where(int(bad[0]))}: ori_w..ori_z has length {norm[bad[0]]:.6g}, "
            "not a unit quaternion (w first)"
        )
    out: Array = matrix_from_quaternion(wxyz)
    return out


def read_joints(path: str | Path, dof: int = 6) -> Array:
    """Joint readings (N×n, rad) from a ``q1..qn`` CSV in degrees."""
    return read_joints_labelled(path, dof).q


@dataclass(frozen=True)
class JointRows:
    """A joints file: readings ``q`` (N×n, rad), the optional ``target`` and ``session``
    labels, and the time, temperature and payload columns (or None)."""

    q: Array
    targets: tuple[str, ...] | None
    sessions: tuple[str, ...] | None
    conditions: Conditions | None


def read_joints_labelled(path: str | Path, dof: int = 6) -> JointRows:
    """Joint readings (N×n, rad), the optional ``target`` and ``session`` labels and the
    ``time_s``, ``temperature_c``, ``payload_kg`` columns."""
    cols = joint_columns(dof)
    t = read_table(path, cols, ",".join(cols))
    return JointRows(
        read_joint_columns(t, dof), _labels(t, "target"), _labels(t, "session"), read_conditions(t)
    )


def format_positions(q: Array, xyz: Array) -> str:
    """CSV text ``q1..qn,x,y,z``: joints in degrees, positions in mm (6 decimals)."""
    dof = q.shape[1]
    lines = [",".join([*joint_columns(dof), "x", "y", "z"])]
    for qi, p in zip(q, xyz, strict=True):
        lines.append(
            ",".join(f"{round(math.degrees(v), 6) + 0.0:.6f}" for v in qi)
            + ","
            + ",".join(f"{round(float(v), 6) + 0.0:.6f}" for v in p)
        )
    return "\n".join(lines) + "\n"
