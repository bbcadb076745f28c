"""Poses drawn at random over the workspace box (``campaign.region = "workspace"``):
the candidates an optimal plan chooses from and the points its expected error is judged
at, reachable ones only (pure).

Target positions are uniform over the box ``workspace_min_mm``..``workspace_max_mm``;
the flange is turned from its orientation at home by a seeded rotation about each axis,
as the cube's poses are; each pose is solved by inverse kinematics of the nominal model
from home and kept if it is within the joint limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array, so3_exp
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel
from cellcal.config import CampaignConfig

#: campaign.region: where the robot will work (and the region label of poses drawn there)
CUBE = "cube"
WORKSPACE = "workspace"
#: ``campaign.region = "workspace"``: this many reachable candidates (the cube's count on
#: the bundled cells) and this many workspace points to judge the prediction at, drawn
#: uniformly over the workspace box and tried in the order drawn until there are enough,
#: or REGION_MAX_DRAWS were tried; the first batch solves this many at once.
REGION_CANDIDATES = 320
REGION_POINTS = 200
REGION_MAX_DRAWS = 4000
REGION_FIRST_BATCH = 400


def orientations(rng: np.random.Generator, R0: Array, n: int, deg: float) -> Array:
    """``n`` flange orientations: ``R0`` turned by up to ``deg`` about each axis."""
    if deg == 0 or n == 0:
        return np.broadcast_to(R0, (n, 3, 3)).copy()
    v = rng.uniform(-1, 1, (n, 3)) * np.radians(deg)
    return np.array([so3_exp(w) @ R0 for w in v])


def box(cfg: CampaignConfig) -> tuple[Array, Array]:
    """The workspace box's corners (mm, base frame)."""
    return np.asarray(cfg.workspace_min_mm), np.asarray(cfg.workspace_max_mm)


def region_text(cfg: CampaignConfig) -> str:
    """Where the plan's expected error is judged (``campaign.region``), in words."""
    if cfg.region == WORKSPACE:
        lo, hi = box(cfg)
        axes = ", ".join(
            f"{a} {a_lo:g}..{a_hi:g}" for a, a_lo, a_hi in zip("xyz", lo, hi, strict=True)
        )
        return f"over the workspace box ({axes} mm)"
    return "in the cube and the validation regions"


@dataclass(frozen=True)
class Drawn:
    """Reachable poses drawn over the workspace box, in the order drawn: the target
    positions (mm, base frame), their joint readings (rad), and how many poses were
    drawn to find them (reachable or not)."""

    points: Array
    q: Array
    drawn: int


def draw_reachable(
    cfg: CampaignConfig,
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    rng: np.random.Generator,
    n: int,
    turn_deg: float,
) -> Drawn:
    """The first ``n`` reachable of poses drawn from ``rng``: target positions uniform
    over the workspace box, the flange turned from its orientation at home by up to
    ``turn_deg`` about each axis (as the cube's poses are); each solved by inverse
    kinematics from home and kept if within the joint limits. At most
    :data:`REGION_MAX_DRAWS` are tried (fewer than ``n`` come back if the robot reaches
    little of the box). The poses are drawn before any is solved, so the result does not
    depend on how many are solved at once."""
    lo, hi = box(cfg)
    R0 = target_kinematics(model, home_q[None], target_offset, jacobian=False).R_flange[0]
    pts = rng.uniform(lo, hi, (REGION_MAX_DRAWS, 3))
    Rs = orientations(rng, R0, REGION_MAX_DRAWS, turn_deg)
    found: list[int] = []
    qs: list[Array] = []
    start = 0
    while start < REGION_MAX_DRAWS and len(found) < n:
        if start == 0:
            size = REGION_FIRST_BATCH
        else:  # as many as the rate so far says are needed, and a fifth more
            rate = max(len(found) / start, 0.02)
            size = math.ceil((n - len(found)) / rate * 1.2) + 10
        stop = min(start + size, REGION_MAX_DRAWS)
        sol = solve(model, target_offset, pts[start:stop], Rs[start:stop], home_q)
        ok = np.flatnonzero(sol.ok)
        found += [start + int(k) for k in ok]
        qs += list(sol.q[ok])
        start = stop
    found, qs = found[:n], qs[:n]
    drawn = found[-1] + 1 if len(found) == n and n > 0 else start
    q = np.array(qs).reshape(-1, model.dof)
    return Drawn(pts[found].reshape(-1, 3), q, drawn)
