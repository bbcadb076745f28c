"""Shared fixtures: the paper's Table 4 points, a random rigid problem factory, and the
bundled simulated cell without its camera rig (campaigns in seconds, for the tests that
are not about the rig)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.config import CellConfig, load_config

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "cellcal" / "data"
#: the bundled cell less its rig: the tracker alone
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"
TABLE4_SRC = DATA / "paper_table4_station1.csv"
TABLE4_DST = DATA / "paper_table4_station2.csv"


def tracker_cell() -> CellConfig:
    """The bundled simulated cell with the tracker alone (its database path as written)."""
    return load_config(TRACKER_CELL, relative_paths=False)


def load_xyz(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=(1, 2, 3))


@pytest.fixture
def table4() -> tuple[np.ndarray, np.ndarray]:
    return load_xyz(TABLE4_SRC), load_xyz(TABLE4_DST)


def rigid_problem(
    seed: int, n: int = 20, noise: float = 0.0, angle_deg: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Random src cloud (mm), true R, t and dst = R src + t + noise."""
    rng = np.random.default_rng(seed)
    P = rng.uniform(-100.0, 100.0, (n, 3)) + rng.uniform(-2000, 2000, 3)
    if angle_deg is None:
        R = Rotation.random(random_state=seed).as_matrix()
    else:
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    t = rng.uniform(-1500.0, 1500.0, 3)
    Q = P @ R.T + t + rng.normal(0.0, noise, (n, 3))
    return P, Q, R, t
