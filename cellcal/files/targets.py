"""Targets for ``cellcal compensate``: ``name,x,y,z`` (mm) with, optionally, the flange
orientation ``ori_w,ori_x,ori_y,ori_z`` (a unit quaternion, w first) and the joints the
robot program uses for the point today ``q1..qn`` (deg), which pick the configuration
the compensated joints stay near; ``payload_kg`` (the payload each point is reached
with, for a model's compliance term)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.errors import FileFormatError
from cellcal.files.csvtable import read_table
from cellcal.files.measurements import (
    joint_columns,
    read_conditions,
    read_joint_columns,
    read_orientations,
)
from cellcal.files.points import read_points


@dataclass(frozen=True)
class Targets:
    """``names``, ``xyz`` (N×3, mm), ``orientations`` (N×3×3 or None) and ``q`` (N×n
    joints, rad, or None)."""

    path: str
    names: tuple[str, ...]
    xyz: Array
    orientations: Array | None
    q: Array | None
    conditions: Conditions | None = None


def read_targets(path: str | Path, dof: int) -> Targets:
    """Read a targets CSV for a robot with ``dof`` joints."""
    points = read_points(path)
    t = read_table(path, ("name", "x", "y", "z"), "name,x,y,z")
    cols = joint_columns(dof)
    q = None
    if t.has(*cols):
        q = read_joint_columns(t, dof)
    elif any(t.has(c) for c in cols):
        raise FileFormatError(f"{t.path}: give all of {', '.join(cols)} or none")
    return Targets(
        points.path, points.names, points.xyz, read_orientations(t), q, read_conditions(t)
    )
