"""Fewer poses: the held-out error of N D-optimal poses against N random poses from the
same candidates and against the paper's 80-pose cube (the peer, measured in the same
run), on the simulated robots, and the cell time each costs at 7 s dwell.

For each robot (the bundled KR 5 arc cell and the UR10e cell) and seed: a perturbed
robot (lengths ±0.3 mm, angles ±0.03°) seen by a tracker (0.01 mm noise); the plan's
candidates (each grid point at four wrist orientations); the calibration from each set
of poses; the RMS error against the noise-free truth at the plan's validation poses
(inside the cube and in regions O1–O5). Goal: the 80-pose accuracy (within 10 %) with
30 poses or fewer.

    .venv/bin/python benchmarks/pose_selection.py
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.random import Generator

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cellcal.calib.identification import calibrate  # noqa: E402
from cellcal.config import load_config  # noqa: E402
from cellcal.daemon.plan import CALIBRATION, VALIDATION, make_plan  # noqa: E402
from cellcal.mocks.robot_truth import TrueCell, measure, random_cell  # noqa: E402
from cellcal.modelfiles import load_model  # noqa: E402

CELLS = {"kuka-kr5-arc": "mock-cell-tracker.toml", "ur10e": "mock-cell-ur10e.toml"}
SIZES = (12, 16, 20, 24, 30, 40)
NOISE_MM = 0.01
DWELL_S = 7.0
#: Seconds a move between neighbouring poses takes (the simulated 60°/s at speed 0.5,
#: about 20° per move), to compare cell times.
MOVE_S = 0.7
RANDOM_DRAWS = 5


@dataclass(frozen=True)
class Row:
    robot: str
    n: int
    optimal_mm: float
    random_mm: float
    cube_mm: float


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def held_out(robot: str, sizes: tuple[int, ...], seeds: tuple[int, ...]) -> list[Row]:
    """Median held-out RMS over ``seeds`` per size: D-optimal, random, and the cube."""
    config = load_config(ROOT / "config" / CELLS[robot], relative_paths=False)
    nominal = load_model(robot).model
    home = np.radians(config.robot.home_deg)
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=float)
    full = make_plan(config.campaign, nominal, home, offset)
    q_cube = np.array([p.q for p in full.poses if p.role == CALIBRATION])
    q_val = np.array([p.q for p in full.poses if p.role == VALIDATION])
    plans = {
        n: make_plan(config.campaign.model_copy(update={"optimal_poses": n}), nominal, home, offset)
        for n in sizes
    }
    pool = make_plan(
        config.campaign.model_copy(update={"optimal_poses": max(sizes)}),
        nominal,
        home,
        offset,
        select=False,
    )
    q_pool = np.array([p.q for p in pool.poses if p.role == CALIBRATION])
    per: dict[tuple[int, str], list[float]] = {}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        cell = random_cell(nominal, rng, target_offset_mm=tuple(offset))

        def error(q: np.ndarray, cell: TrueCell = cell, rng: Generator = rng) -> float:
            m = measure(cell, q, rng, NOISE_MM)
            fit = calibrate(nominal, q, m, np.full_like(m, NOISE_MM), accept=True)
            return _rms(fit.predict(q_val) - cell.positions(q_val))

        per.setdefault((0, "cube"), []).append(error(q_cube))
        for n, plan in plans.items():
            q_opt = np.array([p.q for p in plan.poses if p.role == CALIBRATION])
            per.setdefault((n, "optimal"), []).append(error(q_opt))
            draws = [
                error(q_pool[rng.choice(len(q_pool), n, replace=False)])
                for _ in range(RANDOM_DRAWS)
            ]
            per.setdefault((n, "random"), []).append(float(np.median(draws)))
    cube = float(np.median(per[(0, "cube")]))
    return [
        Row(
            robot,
            n,
            float(np.median(per[(n, "optimal")])),
            float(np.median(per[(n, "random")])),
            cube,
        )
        for n in sizes
    ]


def cell_minutes(n: int) -> float:
    return n * (DWELL_S + MOVE_S) / 60.0


def main() -> None:
    t0 = time.perf_counter()
    seeds = (11, 12, 13, 14, 15)
    print(
        f"held-out RMS at the plans' validation poses (mm), median of {len(seeds)} "
        "simulated robots;"
    )
    print(f"random: median of {RANDOM_DRAWS} draws per robot from the same candidates")
    for robot in CELLS:
        rows = held_out(robot, SIZES, seeds)
        cube = rows[0].cube_mm
        print(
            f"\n{robot}: the paper's 80-pose cube (peer) {cube:.4f} mm, "
            f"{cell_minutes(80):.1f} min of cell time"
        )
        print(f"  {'N':>4} {'D-optimal':>10} {'random':>10} {'optimal/cube':>13} {'cell min':>9}")
        met = None
        for r in rows:
            ratio = r.optimal_mm / r.cube_mm
            print(
                f"  {r.n:>4} {r.optimal_mm:>10.4f} {r.random_mm:>10.4f} {ratio:>12.2f}× "
                f"{cell_minutes(r.n):>9.1f}"
            )
            if met is None and r.n <= 30 and ratio <= 1.10:
                met = r
        if met is not None:
            saved = cell_minutes(80) - cell_minutes(met.n)
            print(
                f"  goal (80-pose accuracy within 10 % with ≤ 30 poses): met at N = {met.n} "
                f"({met.optimal_mm / cube:.2f}× the cube's error), {saved:.1f} min of cell "
                "time saved"
            )
        else:
            best = min((r for r in rows if r.n <= 30), key=lambda r: r.optimal_mm)
            print(
                f"  goal (80-pose accuracy within 10 % with ≤ 30 poses): not met; best "
                f"N = {best.n} at {best.optimal_mm / cube:.2f}× the cube's error"
            )
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
