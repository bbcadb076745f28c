"""Fewer poses: the held-out error of N D-optimal poses against N random poses from the
same candidates and against the paper's 80-pose cube (the peer, measured in the same
run), on the simulated robots, and the cell time each costs at 7 s dwell.

For each robot (the bundled KR 5 arc cell and the UR10e cell) and each of 20 seeds: a
perturbed robot (lengths ±0.3 mm, angles ±0.03°; benchmarks/calibration.py's
``random_cell``) seen by a tracker (0.01 mm noise, its ``measure``); the plan's
candidates (each grid point at four wrist orientations); the calibration from each set
of poses; the RMS error against the noise-free truth at the plan's validation poses
(inside the cube and in regions O1–O5). Cell time: the calibration poses' tour from home
as the plan orders it, 7 s dwell per pose plus each move's largest joint turn at the
cell's joint speed (simulation.joint_speed_deg_s × robot.speed: 15 °/s), as
``cellcal plan`` estimates it. Goal: the 80-pose accuracy (within 10 %) with 30 poses
or fewer.

    .venv/bin/python benchmarks/pose_selection.py
"""

from __future__ import annotations

import math
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
from cellcal.daemon.plan import CALIBRATION, VALIDATION, cell_seconds, make_plan  # noqa: E402
from cellcal.mocks.robot_truth import TrueCell, measure, random_cell  # noqa: E402
from cellcal.modelfiles import load_model  # noqa: E402

CELLS = {"kuka-kr5-arc": "mock-cell-tracker.toml", "ur10e": "mock-cell-ur10e.toml"}
SIZES = (12, 16, 20, 24, 30, 40)
NOISE_MM = 0.01
DWELL_S = 7.0
RANDOM_DRAWS = 3
#: Simulated robots per cell: one robot's held-out error varies by 2× with its noise
#: draw, so the medians need about this many to be stable to 10 %.
SEEDS = tuple(range(11, 31))


@dataclass(frozen=True)
class Row:
    robot: str
    n: int
    optimal_mm: float
    random_mm: float
    cube_mm: float
    minutes: float  # the N chosen poses' cell time
    cube_minutes: float


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
    speed = math.radians(config.simulation.joint_speed_deg_s * config.robot.speed)

    def minutes(q: np.ndarray) -> float:
        return cell_seconds(q, home, speed, DWELL_S) / 60.0

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
            minutes(np.array([p.q for p in plans[n].poses if p.role == CALIBRATION])),
            minutes(q_cube),
        )
        for n in sizes
    ]


def goal(rows: list[Row]) -> str:
    """The goal's line: the smallest N ≤ 30 within 10 % of the cube's error (and from
    which N on every size up to 30 is), with the cell time it saves; or not met."""
    cube = rows[0].cube_mm
    small = [r for r in rows if r.n <= 30]
    within = [r for r in small if r.optimal_mm <= 1.10 * cube]
    head = "goal (80-pose accuracy within 10 % with ≤ 30 poses)"
    if not within:
        best = min(small, key=lambda r: r.optimal_mm)
        return (
            f"{head}: not met; best N = {best.n} at {best.optimal_mm / cube:.2f}× "
            f"the cube's error ({best.optimal_mm:.4f} mm against {cube:.4f} mm)"
        )
    first = within[0]
    steady = next(
        (r for k, r in enumerate(small) if all(x.optimal_mm <= 1.10 * cube for x in small[k:])),
        None,
    )
    after = (
        f"; within 10 % at every N from {steady.n} to 30"
        if steady is not None and steady.n != first.n
        else ""
    )
    return (
        f"{head}: met at N = {first.n} ({first.optimal_mm:.4f} mm, "
        f"{first.optimal_mm / cube:.2f}× the cube's {cube:.4f} mm), "
        f"{first.cube_minutes - first.minutes:.1f} min of cell time saved "
        f"({first.minutes:.1f} instead of {first.cube_minutes:.1f}){after}"
    )


def main() -> None:
    t0 = time.perf_counter()
    seeds = SEEDS
    print(
        f"held-out RMS at the plans' validation poses (mm), median of {len(seeds)} "
        "simulated robots;"
    )
    print(f"random: median of {RANDOM_DRAWS} draws per robot from the same candidates")
    print("ratio: median D-optimal RMS / median 80-pose RMS")
    print(
        f"cell time: the calibration poses' tour at {DWELL_S:g} s dwell, moves at the "
        "cell's joint speed"
    )
    for robot in CELLS:
        rows = held_out(robot, SIZES, seeds)
        cube = rows[0].cube_mm
        print(
            f"\n{robot}: the paper's 80-pose cube (peer) {cube:.4f} mm, "
            f"{rows[0].cube_minutes:.1f} min of cell time"
        )
        print(f"  {'N':>4} {'D-optimal':>10} {'random':>10} {'optimal/cube':>13} {'cell min':>9}")
        for r in rows:
            print(
                f"  {r.n:>4} {r.optimal_mm:>10.4f} {r.random_mm:>10.4f} "
                f"{r.optimal_mm / cube:>12.2f}× {r.minutes:>9.1f}"
            )
        print(f"  {goal(rows)}")
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
