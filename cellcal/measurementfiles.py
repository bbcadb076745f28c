"""The calibration data files of the public contract, read at the edge.

Measurements: ``q1..qn,x,y,z`` — joint readings in degrees as the controller reports
them, target position in mm in the instrument frame — with an optional ``name`` column
and optional ``sx,sy,sz`` (1σ, mm). Joints: ``q1..qn`` (deg). Angles become radians here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.csvtable import Table, read_table
from cellcal.errors import FileFormatError

#: More rows than this are refused: the fit's Jacobian would need gigabytes.
MAX_ROWS = 100_000


@dataclass(frozen=True)
class Measurements:
    """Rows of a measurement file: ``q`` (N×n, rad), ``xyz`` (N×3, mm), ``sigma`` (N×3 mm
    or None) and ``names`` (the name column, or row numbers)."""

    path: str
    names: tuple[str, ...]
    q: Array
    xyz: Array
    sigma: Array | None


def _joint_columns(dof: int) -> tuple[str, ...]:
    return tuple(f"q{i}" for i in range(1, dof + 1))


def _joints(t: Table, dof: int) -> Array:
    cols = _joint_columns(dof)
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
    cols = _joint_columns(dof)
    expected = ",".join(cols) + ",x,y,z"
    t = read_table(path, (*cols, "x", "y", "z"), expected)
    if len(t.rows) > MAX_ROWS:
        raise FileFormatError(
            f"{t.path}: {len(t.rows)} rows; a calibration takes at most {MAX_ROWS} "
            "(a campaign measures hundreds to a few thousand poses)"
        )
    q = _joints(t, dof)
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
    return Measurements(t.path, names, q, xyz, sigma)


def read_joints(path: str | Path, dof: int = 6) -> Array:
    """Joint readings (N×n, rad) from a ``q1..qn`` CSV in degrees."""
    cols = _joint_columns(dof)
    t = read_table(path, cols, ",".join(cols))
    return _joints(t, dof)


def format_positions(q: Array, xyz: Array) -> str:
    """CSV text ``q1..qn,x,y,z``: joints in degrees, positions in mm (6 decimals)."""
    dof = q.shape[1]
    lines = [",".join([*_joint_columns(dof), "x", "y", "z"])]
    for qi, p in zip(q, xyz, strict=True):
        lines.append(
            ",".join(f"{round(math.degrees(v), 6) + 0.0:.6f}" for v in qi)
            + ","
            + ",".join(f"{round(float(v), 6) + 0.0:.6f}" for v in p)
        )
    return "\n".join(lines) + "\n"
