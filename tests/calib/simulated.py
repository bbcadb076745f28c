"""Simulated calibration data shared by the calibration tests (cached per process)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from cellcal.calib.geometry import so3_exp
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import target_kinematics
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import TrueCell, measure, random_cell, random_joints

NOISE_MM = 0.01
TOOL_IK = np.array([25.0, -40.0, 130.0])
SEED_Q = np.radians([0, -30, 40, 0, -20, 0])
CUBE_CENTRE = np.array([750.0, 0.0, 1000.0])


@dataclass(frozen=True)
class Data:
    cell: TrueCell
    q: np.ndarray
    m: np.ndarray
    q_val: np.ndarray
    m_val_true: np.ndarray


@cache
def well_spread(robot: str, seed: int = 1, n: int = 80, noise: float = NOISE_MM) -> Data:
    nominal = load_model(robot).model
    rng = np.random.default_rng(seed)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, n)
    m = measure(cell, q, rng, noise)
    q_val = random_joints(nominal, rng, 300)
    return Data(cell, q, m, q_val, cell.positions(q_val))


def cube_joints(rng: np.random.Generator, n_side=(4, 4, 5), vary_deg: float = 0.0, random_points=0):
    """The paper's 200 mm cube at (750, 0, 1000) on a KR 5 arc, by IK; ``vary_deg`` turns
    the flange by up to that much about each axis per point."""
    nominal = load_model("kuka-kr5-arc").model
    R0 = target_kinematics(nominal, SEED_Q[None], TOOL_IK, jacobian=False).R_flange[0]
    if random_points:
        pts = CUBE_CENTRE + rng.uniform(-100, 100, (random_points, 3))
    else:
        axes = [np.linspace(-100, 100, k) for k in n_side]
        pts = CUBE_CENTRE + np.array([[x, y, z] for x in axes[0] for y in axes[1] for z in axes[2]])
    if vary_deg:
        R = np.array([so3_exp(rng.uniform(-1, 1, 3) * np.radians(vary_deg)) @ R0 for _ in pts])
    else:
        R = R0
    sol = solve(nominal, TOOL_IK, pts, R, SEED_Q)
    assert sol.ok.all()
    return sol.q


@cache
def paper_cube(vary_deg: float, seed: int = 5) -> Data:
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(seed)
    cell = random_cell(nominal, np.random.default_rng(seed + 1))
    q = cube_joints(rng, vary_deg=vary_deg)
    m = measure(cell, q, rng, NOISE_MM)
    q_val = cube_joints(rng, vary_deg=vary_deg, random_points=150)
    return Data(cell, q, m, q_val, cell.positions(q_val))
