"""Benchmark of kinematic calibration (cellcal.calib.identification): accuracy and speed.

Prints, in one run:

1. cellcal against the peer FIGAROH (calibration on Pinocchio) on the same simulated data:
   a robot with injected errors (lengths ±0.3 mm, angles ±0.03°, β on the parallel pair),
   an unknown sensor frame about 3 m away and an unknown target offset, noise
   0.01 mm per axis, 80 well-spread calibration poses and 500 held-out poses. Held-out
   RMS / mean / max error against the noise-free truth and against noisy measurements,
   the "before" baseline (nominal geometry, best-fit sensor frame and target offset),
   wall time of the calibration and number of identified parameters.
2. The noise-limited bound: the first-order RMS error at the held-out poses,
   E|δp|² = trace(J(x) C J(x)ᵀ) with C the covariance of the identified parameters for
   the TRUE noise σ², against the measured held-out error; and the before/after ratio.
3. The paper's case: the 80-point 200 mm cube held at one flange orientation, against the
   same cube with the wrist orientation varied per point: conditioning, identifiability,
   held-out errors inside the cube and on well-spread poses outside it.
4. Scaling of the calibration time and memory with the number of poses, 80 to 20 000,
   against a plain scipy least-squares fit of the same parameters (and FIGAROH where
   affordable): benchmarks/calibration_scaling.py.
5. A conclusion computed from the numbers above.

FIGAROH is a benchmark-only extra: it is imported here and nowhere else. Without it the
FIGAROH columns are skipped with a line saying how to install it. Run from the
repository root with a Python that has cellcal's dependencies (and FIGAROH):

    .venv/bin/python benchmarks/calibration.py            # defaults, well under a minute
    .venv/bin/python benchmarks/calibration.py --quick    # a smaller run
    PYTHONPATH=. /path/to/figaroh-venv/bin/python benchmarks/calibration.py  # with FIGAROH

Nothing here asserts anything about time; the numbers are ratios measured in one run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import TypeVar

import numpy as np
from calibration_cases import Bound, CubeCase, cube_case, noise_bound, print_bound, print_cube
from calibration_scaling import FIGAROH_BUDGET_S, ScaleRow, print_scaling, scaling, speed_verdict
from calibration_scenario import (
    BOUND_TARGET,
    IMPROVEMENT_TARGET,
    N_CALIBRATION,
    N_HELD_OUT,
    PAPER_CL_MM,
    PAPER_OTHER_MM,
    SIGMA_MM,
    TIME_80_TARGET_S,
    TIME_6000_TARGET_S,
    TOOL_MM,
    WRIST_SPREAD_DEG,
    met,
)
from calibration_versus import Comparison, compare, print_comparison
from figaroh_peer import Figaroh, import_figaroh
from numpy.typing import NDArray
from real_data import print_real  # benchmarks/real_data.py, beside this script

from cellcal.errors import CellcalError

Array = NDArray[np.float64]
T = TypeVar("T")

# --------------------------------------------------------------------------- 5. conclusion


def print_conclusion(
    comps: list[Comparison],
    b: Bound,
    cubes: list[CubeCase],
    rows: list[ScaleRow],
    fg: Figaroh | None,
) -> None:
    print()
    print("== 5. Conclusion (computed from the numbers above)")
    for c in comps:
        line = (
            f"   {c.robot}: cellcal identifies {len(c.result.identifiability.identified)} "
            f"parameters in {c.cellcal_s * 1e3:.1f} ms and predicts held-out poses within "
            f"{c.cellcal.truth.rms:.4f} mm RMS of the truth (before: {c.before.truth.rms:.3f} mm)"
        )
        if c.figaroh is not None and c.figaroh_acc is not None:
            e = c.figaroh_acc.truth.rms / c.cellcal.truth.rms
            t = c.figaroh.total_s / c.cellcal_s
            better = "more" if e >= 1.0 else "less"
            line += (
                f"; FIGAROH identifies {len(c.figaroh.names)} in {c.figaroh.total_s * 1e3:.0f} ms "
                f"({t:.0f}× the time) and its held-out error is {e:.2f}× cellcal's ({better} "
                "error)"
            )
            if c.noise_free_figaroh_mm > 100 * max(c.noise_free_cellcal_mm, 1e-9):
                line += (
                    f"; on noise-free data it keeps {c.noise_free_figaroh_mm:.4f} mm of residual"
                    " (its parameter set does not span the injected errors)"
                )
        if c.figaroh_tool is not None and c.figaroh_tool_acc is not None:
            line += (
                f"; given the true target offset in its URDF, FIGAROH selects "
                f"{len(c.figaroh_tool.names)} parameters and its held-out error becomes "
                f"{c.figaroh_tool_acc.truth.rms:.4f} mm"
            )
        print(line + ".")
    if fg is None:
        print("   FIGAROH was not available: install it (pip install figaroh) for the comparison.")
    r = max(b.measured_mm, b.mc_rms_mm) / b.bound_mm
    imp = b.before_mm / b.measured_mm
    print(
        f"   cellcal is noise-limited: held-out error {r:.2f}× the first-order bound (target "
        f"≤ {BOUND_TARGET:g}×: {met(r <= BOUND_TARGET)}), {imp:.0f}× better than the nominal "
        f"model (target ≥ {IMPROVEMENT_TARGET:g}×: {met(imp >= IMPROVEMENT_TARGET)}); the paper "
        f"reports {PAPER_OTHER_MM} → {PAPER_CL_MM} mm ({PAPER_OTHER_MM / PAPER_CL_MM:.2f}×, "
        "between two methods)."
    )
    fixed, varied = cubes
    lost = sorted(set(fixed.result.unidentifiable) - set(varied.result.unidentifiable))
    print(
        f"   The paper's fixed-orientation cube has condition number "
        f"{fixed.result.condition_number:.3g} against {varied.result.condition_number:.3g} with "
        f"the wrist varied ({fixed.result.condition_number / varied.result.condition_number:.0f}×"
        f"); it leaves {', '.join(lost) or 'nothing more'} unidentifiable. Inside the cube both "
        f"predict within {fixed.inside_after.rms:.4f} / {varied.inside_after.rms:.4f} mm, but "
        f"outside it the fixed-orientation model is off by {fixed.outside_after.rms:.1f} mm RMS "
        f"against {varied.outside_after.rms:.3f} mm."
    )
    if "target_offset_x" in fixed.result.unidentifiable:
        off = np.linalg.norm(np.asarray(TOOL_MM) - fixed.result.target_offset)
        print(
            "   At one flange orientation the target offset moves every point by the same "
            "vector, so the sensor translation absorbs it: the model keeps the nominal "
            f"offset, {off:.1f} mm from the true one, and is valid at that orientation only."
        )
    t80 = comps[0].cellcal_s
    big = rows[-1]
    line = (
        f"   Speed: {t80 * 1e3:.1f} ms for {N_CALIBRATION} poses (target ≤ "
        f"{TIME_80_TARGET_S * 1e3:g} ms: {met(t80 <= TIME_80_TARGET_S)}), "
        f"{big.cellcal_s:.2f} s for {big.n} poses"
    )
    if big.n >= 6000:
        line += f" (target ≤ {TIME_6000_TARGET_S:g} s: {met(big.cellcal_s <= TIME_6000_TARGET_S)})"
    fr = [x for x in rows if x.figaroh is not None]
    if fr:
        ratios = ", ".join(
            f"{x.figaroh.total_s / x.cellcal_s:.0f}× at {x.n}" for x in fr if x.figaroh is not None
        )
        line += f"; FIGAROH takes {ratios} poses"
    print(line + ".")
    print(f"   Speed: {speed_verdict(rows)}.")


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a smaller, faster run")
    ap.add_argument("--seed", type=int, default=20180709, help="numpy SeedSequence seed")
    ap.add_argument("--no-figaroh", action="store_true", help="skip the FIGAROH peer")
    args = ap.parse_args(argv)

    quick = args.quick
    robots = ("kuka-kr5-arc",) if quick else ("kuka-kr5-arc", "ur10e")
    repeats = 3 if quick else 7
    fg_repeats = 1 if quick else 3
    draws = 5 if quick else 20
    n_cube_val = 200 if quick else N_HELD_OUT
    sizes = (80, 1000, 6000) if quick else (80, 300, 1000, 6000, 20000)
    fg_sizes = (80,) if quick else (80, 1000)
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(args.seed).spawn(8)]

    t_start = time.perf_counter()
    print(
        f"cellcal calibration benchmark (numpy {np.__version__}, seed {args.seed}"
        f"{', quick' if quick else ''})"
    )
    fg: Figaroh | None = None
    if args.no_figaroh:
        print("FIGAROH: skipped (--no-figaroh)")
    else:
        fg, why = import_figaroh()
        if fg is None:
            print(
                f"FIGAROH: not importable ({why}); install it into this environment with "
                "`pip install figaroh` (or `make bench`) for the comparison — running the rest."
            )
        else:
            print(f"FIGAROH {fg.version} (pin {fg.pin_version}), import {fg.import_s:.2f} s")

    with tempfile.TemporaryDirectory(prefix="cellcal-bench-") as tmp:
        workdir = Path(tmp)
        print()
        print(
            f"== 1. cellcal vs FIGAROH on the same data: errors ±0.3 mm / ±0.03° (β on parallel "
            f"rows), σ = {SIGMA_MM:g} mm per axis,"
        )
        print(
            f"   {N_CALIBRATION} calibration poses and {N_HELD_OUT} held-out poses "
            "(random_joints); before = nominal geometry with best-fit sensor frame and "
            "target offset"
        )
        comps = []
        for k, robot in enumerate(robots):
            c = compare(robot, streams[k], fg, workdir, repeats, fg_repeats)
            print_comparison(c, fg)
            comps.append(c)

        main_cmp = comps[0]
        b = noise_bound(main_cmp, streams[3], draws)
        print_bound(main_cmp, b)

        try:
            cubes = [
                cube_case("fixed orientation", False, main_cmp, streams[4], n_cube_val),
                cube_case(f"varied ±{WRIST_SPREAD_DEG:g}°", True, main_cmp, streams[5], n_cube_val),
            ]
        except CellcalError as exc:
            print(f"\n== 3. The paper's case failed: {exc}")
            return 1
        print_cube(cubes, main_cmp, n_cube_val)

        sc = main_cmp.sc
        rows = scaling(
            sc.nominal,
            sc.cell,
            SIGMA_MM,
            streams[6],
            sizes,
            fg_sizes,
            fg,
            workdir,
            repeats,
            fg_repeats,
        )
        print_scaling(rows, main_cmp.robot)
        if fg is not None:
            ran = [r.n for r in rows if r.figaroh is not None]
            print(
                f"   FIGAROH is run at {', '.join(map(str, ran)) or 'no size'} poses only "
                f"(budget ~{FIGAROH_BUDGET_S:g} s a size{', --quick' if quick else ''}); "
                "'expected' extrapolates its measured time per pose linearly."
            )

    print_conclusion(comps, b, cubes, rows, fg)
    print_real()
    print(f"\n(total wall time {time.perf_counter() - t_start:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
