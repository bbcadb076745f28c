"""Fewer poses: the held-out error of N D-optimal and N I-optimal poses against N random
poses from the same candidates and against the paper's 80-pose cube (the peer, measured
in the same run), on the simulated robots, and the cell time each costs at 7 s dwell.

For each robot (the bundled KR 5 arc cell and the UR10e cell) and each of 20 seeds: a
perturbed robot (lengths ±0.3 mm, angles ±0.03°; benchmarks/calibration.py's
``random_cell``) seen by a tracker (0.01 mm noise, its ``measure``); the plan's
candidates (each grid point at four wrist orientations); the calibration from each set
of poses; the RMS error against the noise-free truth at the plan's validation poses
(inside the cube and in regions O1–O5). Cell time: the calibration poses' tour from home
as the plan orders it, 7 s dwell per pose plus each move's largest joint turn at the
cell's joint speed (simulation.joint_speed_deg_s × robot.speed: 15 °/s), as
``cellcal plan`` estimates it. Beside each measured error: the plan's own expectation
(``cellcal plan``'s expected RMS in the cube and the validation regions × the noise),
which judges the same regions at other points. Goal: the 80-pose accuracy (within 10 %)
with 30 poses or fewer.

Then the whole workspace (``campaign.region = "workspace"``): for each robot, the
held-out error at poses drawn at random over the cell's workspace box (reachable ones,
another seed than the plan's) of N optimal poses chosen from candidates drawn over the
box, against its peers measured in the same run: N optimal poses of the cube's
candidates, N poses drawn at random over the same box (median of three draws per robot)
and the 80-pose cube.

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
from cellcal.campaign.plan import (  # noqa: E402
    CALIBRATION,
    VALIDATION,
    cell_seconds,
    expected_rms,
    make_plan,
    workspace_poses,
)
from cellcal.campaign.plan_region import draw_reachable  # noqa: E402
from cellcal.config import CampaignConfig, load_config  # noqa: E402
from cellcal.files.models import load_model  # noqa: E402
from cellcal.mocks.robot_truth import TrueCell, measure, random_cell  # noqa: E402

CELLS = {"kuka-kr5-arc": "mock-cell-tracker.toml", "ur10e": "mock-cell-ur10e.toml"}
SIZES = (12, 16, 20, 24, 30, 40)
NOISE_MM = 0.01
DWELL_S = 7.0
RANDOM_DRAWS = 3
#: Simulated robots per cell: one robot's held-out error varies by 2× with its noise
#: draw, so the medians need about this many to be stable to 10 %.
SEEDS = tuple(range(11, 31))


CRITERIA = ("D", "I")
#: Over the workspace box: the poses judged (as the issue measured), and their seed
#: (apart from the plan's candidates and workspace points).
HELD_OUT_POINTS = 500
HELD_OUT_SEED = 104729
REGION_SIZES = (24, 30)


@dataclass(frozen=True)
class Row:
    """One size N: the median held-out RMS (mm) of the N D-optimal (``optimal_mm``),
    N I-optimal and N random poses and of the cube, each plan's expected RMS (mm), and
    the cell time (min) of the chosen poses (D, I) and of the cube."""

    robot: str
    n: int
    optimal_mm: float
    random_mm: float
    cube_mm: float
    minutes: float
    cube_minutes: float
    i_optimal_mm: float = float("nan")
    i_minutes: float = float("nan")
    expected_mm: tuple[float, float, float] = (float("nan"),) * 3  # D, I, cube
    #: the cube's √(mean square) over the robots: what the expectation predicts (the
    #: median of a few correlated errors' RMS lies below it)
    cube_rms_mm: float = float("nan")

    def of(self, criterion: str) -> tuple[float, float]:
        """The criterion's held-out RMS and cell time."""
        if criterion == "I":
            return self.i_optimal_mm, self.i_minutes
        return self.optimal_mm, self.minutes


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def held_out(robot: str, sizes: tuple[int, ...], seeds: tuple[int, ...]) -> list[Row]:
    """Median held-out RMS over ``seeds`` per size: D-optimal, I-optimal, random, and
    the cube."""
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

    def chosen(n: int, criterion: str) -> np.ndarray:
        cfg = config.campaign.model_copy(
            update={"optimal_poses": n, "optimal_criterion": criterion}
        )
        plan = make_plan(cfg, nominal, home, offset)
        return np.array([p.q for p in plan.poses if p.role == CALIBRATION])

    plans = {(n, c): chosen(n, c) for n in sizes for c in CRITERIA}
    workspace = workspace_poses(config.campaign, nominal, home, offset)

    def expected_mm(q: np.ndarray) -> float:
        value = expected_rms(nominal, q, offset, workspace)
        return float("nan") if value is None else value * NOISE_MM

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
        for (n, criterion), q_opt in plans.items():
            per.setdefault((n, criterion), []).append(error(q_opt))
        for n in sizes:
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
            float(np.median(per[(n, "D")])),
            float(np.median(per[(n, "random")])),
            cube,
            minutes(plans[(n, "D")]),
            minutes(q_cube),
            float(np.median(per[(n, "I")])),
            minutes(plans[(n, "I")]),
            (expected_mm(plans[(n, "D")]), expected_mm(plans[(n, "I")]), expected_mm(q_cube)),
            float(np.sqrt(np.mean(np.square(per[(0, "cube")])))),
        )
        for n in sizes
    ]


@dataclass(frozen=True)
class RegionRow:
    """N poses judged over the workspace box: the median held-out RMS (mm) of N
    ``criterion``-optimal poses from candidates drawn over the box (``workspace_mm``) and
    from the cube's candidates (``cube_optimal_mm``), of N poses drawn at random over the
    box (``random_mm``: random picks of the box's candidates, the median of RANDOM_DRAWS
    per robot) and of the 80-pose cube;
    each plan's expectation over the box (mm: workspace, cube's optimal, 80-pose cube)
    and the cell time (min) of the optimal poses (workspace, cube); ``at_validation_mm``:
    the same calibrations' median RMS at the plan's validation poses (in the cube and
    O1–O5, as the first table judges): workspace optimal, cube's optimal, 80-pose cube."""

    robot: str
    n: int
    criterion: str
    workspace_mm: float
    cube_optimal_mm: float
    random_mm: float
    cube_mm: float
    expected_mm: tuple[float, float, float]
    minutes: tuple[float, float]
    held_out: int
    at_validation_mm: tuple[float, float, float] = (float("nan"),) * 3


def over_workspace(
    robot: str,
    sizes: tuple[int, ...],
    seeds: tuple[int, ...],
    criteria: tuple[str, ...] = CRITERIA,
    points: int = HELD_OUT_POINTS,
) -> list[RegionRow]:
    """Median held-out RMS over ``seeds`` at ``points`` reachable poses drawn over the
    workspace box, per criterion and size: optimal poses of the box's candidates and of
    the cube's, random picks of the box's candidates (reachable poses drawn over the
    box), and the 80-pose cube."""
    config = load_config(ROOT / "config" / CELLS[robot], relative_paths=False)
    nominal = load_model(robot).model
    home = np.radians(config.robot.home_deg)
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=float)
    box = config.campaign.model_copy(update={"region": "workspace"})
    speed = math.radians(config.simulation.joint_speed_deg_s * config.robot.speed)
    judged = workspace_poses(box, nominal, home, offset)

    def calibration_q(cfg: CampaignConfig, select: bool = True) -> np.ndarray:
        plan = make_plan(cfg, nominal, home, offset, select=select, workspace=judged)
        return np.array([p.q for p in plan.poses if p.role == CALIBRATION])

    def minutes(q: np.ndarray) -> float:
        return cell_seconds(q, home, speed, DWELL_S) / 60.0

    q_cube = calibration_q(config.campaign)
    full = make_plan(config.campaign, nominal, home, offset)
    q_val = np.array([p.q for p in full.poses if p.role == VALIDATION])
    plans = {
        (n, criterion, region): calibration_q(
            box.model_copy(
                update={"optimal_poses": n, "optimal_criterion": criterion, "region": region}
            )
        )
        for n in sizes
        for criterion in criteria
        for region in ("workspace", "cube")
    }
    pool = calibration_q(box.model_copy(update={"optimal_poses": max(sizes)}), select=False)
    held = draw_reachable(
        box,
        nominal,
        home,
        offset,
        np.random.default_rng([box.seed + HELD_OUT_SEED, 2]),
        points,
        box.orientation_variation_deg,
    ).q

    def expected_mm(q: np.ndarray) -> float:
        value = expected_rms(nominal, q, offset, judged)
        return float("nan") if value is None else value * NOISE_MM

    per: dict[tuple[int, str, str], list[float]] = {}
    at_val: dict[tuple[int, str, str], list[float]] = {}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        cell = random_cell(nominal, rng, target_offset_mm=tuple(offset))

        def error(
            q: np.ndarray,
            key: tuple[int, str, str] | None = None,
            cell: TrueCell = cell,
            rng: Generator = rng,
        ) -> float:
            m = measure(cell, q, rng, NOISE_MM)
            fit = calibrate(nominal, q, m, np.full_like(m, NOISE_MM), accept=True)
            if key is not None:
                at_val.setdefault(key, []).append(_rms(fit.predict(q_val) - cell.positions(q_val)))
            return _rms(fit.predict(held) - cell.positions(held))

        per.setdefault((0, "", "cube"), []).append(error(q_cube, (0, "", "cube")))
        for key, q in plans.items():
            per.setdefault(key, []).append(error(q, key))
        for n in sizes:
            draws = [
                error(pool[rng.choice(len(pool), n, replace=False)]) for _ in range(RANDOM_DRAWS)
            ]
            per.setdefault((n, "", "random"), []).append(float(np.median(draws)))

    def median(key: tuple[int, str, str]) -> float:
        return float(np.median(per[key]))

    return [
        RegionRow(
            robot,
            n,
            criterion,
            median((n, criterion, "workspace")),
            median((n, criterion, "cube")),
            median((n, "", "random")),
            median((0, "", "cube")),
            (
                expected_mm(plans[(n, criterion, "workspace")]),
                expected_mm(plans[(n, criterion, "cube")]),
                expected_mm(q_cube),
            ),
            (minutes(plans[(n, criterion, "workspace")]), minutes(plans[(n, criterion, "cube")])),
            len(held),
            (
                float(np.median(at_val[(n, criterion, "workspace")])),
                float(np.median(at_val[(n, criterion, "cube")])),
                float(np.median(at_val[(0, "", "cube")])),
            ),
        )
        for criterion in criteria
        for n in sizes
    ]


def print_over_workspace(seeds: tuple[int, ...]) -> None:
    """The whole-workspace comparison for every robot and criterion."""
    print(
        f"\nover the workspace box: held-out RMS (mm) at {HELD_OUT_POINTS} reachable poses "
        f"drawn over each cell's box, median of {len(seeds)} simulated robots; (expected): "
        "the plan's own figure over the box"
    )
    for robot in CELLS:
        config = load_config(ROOT / "config" / CELLS[robot], relative_paths=False)
        lo, hi = config.campaign.workspace_min_mm, config.campaign.workspace_max_mm
        box = ", ".join(f"{a} {x:g}..{y:g}" for a, x, y in zip("xyz", lo, hi, strict=True))
        print(f"\n{robot}, box {box} mm:")
        print(
            f"  {'':>6} {'N':>3} {'box optimal (expected)':>24} {'min':>5} "
            f"{'cube optimal (expected)':>25} {'min':>5} {'box / cube':>10} "
            f"{'random':>8} {'box / random':>12}   at the validation poses: box, cube opt."
        )
        rows = over_workspace(robot, REGION_SIZES, seeds)
        for r in rows:
            print(
                f"  {r.criterion + '-opt':>6} {r.n:>3} {r.workspace_mm:>14.4f} "
                f"({r.expected_mm[0]:.4f}) {r.minutes[0]:>5.1f} {r.cube_optimal_mm:>15.4f} "
                f"({r.expected_mm[1]:.4f}) {r.minutes[1]:>5.1f} "
                f"{r.workspace_mm / r.cube_optimal_mm:>9.2f}× {r.random_mm:>8.4f} "
                f"{r.workspace_mm / r.random_mm:>11.2f}×   "
                f"{r.at_validation_mm[0]:.4f}, {r.at_validation_mm[1]:.4f}"
            )
        print(
            f"  80-pose cube (peer of both): {rows[0].cube_mm:.4f} mm "
            f"(expected {rows[0].expected_mm[2]:.4f}); at the validation poses "
            f"{rows[0].at_validation_mm[2]:.4f} mm"
        )


def goal(rows: list[Row], criterion: str) -> str:
    """The goal's line for one criterion: the smallest N ≤ 30 within 10 % of the cube's
    error (and from which N on every size up to 30 is), with the cell time it saves; or
    not met."""
    cube = rows[0].cube_mm
    small = [r for r in rows if r.n <= 30]
    within = [r for r in small if r.of(criterion)[0] <= 1.10 * cube]
    head = f"goal, {criterion}-optimal (80-pose accuracy within 10 % with ≤ 30 poses)"
    if not within:
        best = min(small, key=lambda r: r.of(criterion)[0])
        mm = best.of(criterion)[0]
        return (
            f"{head}: not met; best N = {best.n} at {mm / cube:.2f}× "
            f"the cube's error ({mm:.4f} mm against {cube:.4f} mm)"
        )
    first = within[0]
    mm, minutes = first.of(criterion)
    steady = next(
        (
            r
            for k, r in enumerate(small)
            if all(x.of(criterion)[0] <= 1.10 * cube for x in small[k:])
        ),
        None,
    )
    after = (
        f"; within 10 % at every N from {steady.n} to 30"
        if steady is not None and steady.n != first.n
        else ""
    )
    return (
        f"{head}: met at N = {first.n} ({mm:.4f} mm, {mm / cube:.2f}× the cube's "
        f"{cube:.4f} mm), {first.cube_minutes - minutes:.1f} min of cell time saved "
        f"({minutes:.1f} instead of {first.cube_minutes:.1f}){after}"
    )


def main() -> None:
    t0 = time.perf_counter()
    seeds = SEEDS
    print(
        f"held-out RMS at the plans' validation poses (mm), median of {len(seeds)} "
        "simulated robots;"
    )
    print(f"random: median of {RANDOM_DRAWS} draws per robot from the same candidates")
    print("ratio: median optimal RMS / median 80-pose RMS; (expected): the plan's own figure")
    print(
        f"cell time: the calibration poses' tour at {DWELL_S:g} s dwell, moves at the "
        "cell's joint speed"
    )
    for robot in CELLS:
        rows = held_out(robot, SIZES, seeds)
        cube = rows[0].cube_mm
        print(
            f"\n{robot}: the paper's 80-pose cube (peer) {cube:.4f} mm, "
            f"{rows[0].cube_minutes:.1f} min of cell time; √(mean square) over the robots "
            f"{rows[0].cube_rms_mm:.4f} mm, expected {rows[0].expected_mm[2]:.4f} mm"
        )
        print(
            f"  {'N':>4} {'random':>8}   {'D-optimal (expected)':>21} {'/cube':>6} {'min':>5}"
            f"   {'I-optimal (expected)':>21} {'/cube':>6} {'min':>5}"
        )
        for r in rows:
            print(
                f"  {r.n:>4} {r.random_mm:>8.4f}   {r.optimal_mm:>10.4f} ({r.expected_mm[0]:.4f}) "
                f"{r.optimal_mm / cube:>5.2f}× {r.minutes:>5.1f}   "
                f"{r.i_optimal_mm:>10.4f} ({r.expected_mm[1]:.4f}) "
                f"{r.i_optimal_mm / cube:>5.2f}× {r.i_minutes:>5.1f}"
            )
        for criterion in CRITERIA:
            print(f"  {goal(rows, criterion)}")
    print_over_workspace(seeds)
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
