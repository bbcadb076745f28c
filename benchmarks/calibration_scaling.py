"""Section 4 of benchmarks/calibration.py: calibration time and memory against the number
of poses, cellcal beside two scipy peers and FIGAROH, on the same simulated data.

- **plain**: what anyone with scipy would write (benchmarks/plain_fit.py) —
  ``least_squares(method="lm")`` with scipy's finite-difference Jacobian, over the
  parameters cellcal identified, from cellcal's closed-form start. The goal: cellcal
  at least :data:`PLAIN_SPEED_GOAL`× faster at every size from 80 to 20 000 poses, with
  no more memory.
- **scipy + J**: the same fit given cellcal's analytic Jacobian — the strongest scipy peer
  one can build from cellcal's own parts, shown for honesty (no goal).

Times are the best of several runs, the runs of cellcal and its peers interleaved so a
noisy neighbour slows them alike; memory is the peak of Python allocations
(tracemalloc, which numpy reports to) in a separate run of each.
"""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from figaroh_peer import Figaroh, FigarohRun, run_figaroh
from numpy.typing import NDArray
from plain_fit import plain_fit
from scipy.optimize import least_squares

from cellcal.calib.error_model import Groups, ParameterSpec, apply
from cellcal.calib.identification import calibrate
from cellcal.calib.observations import Data, initial_state
from cellcal.calib.robot_model import RobotModel
from cellcal.mocks.robot_truth import TrueCell, measure, random_joints

Array = NDArray[np.float64]

PLAIN_SPEED_GOAL = 2.0
FIGAROH_BUDGET_S = 30.0


def _peak_bytes(fn: Callable[[], Any]) -> int:
    tracemalloc.start()
    try:
        fn()
        return int(tracemalloc.get_traced_memory()[1])
    finally:
        tracemalloc.stop()


def _best_interleaved(fns: list[Callable[[], Any]], repeats: int) -> list[float]:
    best = [float("inf")] * len(fns)
    for _ in range(repeats):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best


def scipy_with_jacobian(
    nominal: RobotModel, q: Array, measured: Array, specs: tuple[ParameterSpec, ...]
) -> float:
    """scipy's LM with cellcal's analytic Jacobian; the in-sample RMS (mm) it reaches."""
    g = Groups.single(len(q))
    start = initial_state(nominal, q, measured, g)
    data = Data(q, measured, g)

    def fun(x: Array) -> Array:
        out: Array = data.residuals(apply(start, specs, x)).ravel()
        return out

    def jac(x: Array) -> Array:
        out: Array = -data.jacobian(apply(start, specs, x), specs).reshape(-1, len(specs))
        return out

    res = least_squares(fun, np.zeros(len(specs)), jac=jac, method="lm")
    return float(np.sqrt(np.mean(np.sum(res.fun.reshape(-1, 3) ** 2, axis=1))))


@dataclass(frozen=True)
class ScaleRow:
    """One size: wall times (s, best of ``repeats``), peak memory (bytes), in-sample RMS
    (mm) of cellcal and the plain fit; the scipy + J time; FIGAROH's run or why not."""

    n: int
    repeats: int
    cellcal_s: float
    cellcal_bytes: int
    rms_after: float
    plain_s: float
    plain_bytes: int
    plain_rms: float
    jacobian_s: float
    figaroh: FigarohRun | None
    figaroh_note: str

    @property
    def plain_ratio(self) -> float:
        return self.plain_s / self.cellcal_s


def scaling(
    nominal: RobotModel,
    cell: TrueCell,
    sigma_mm: float,
    rng: np.random.Generator,
    sizes: tuple[int, ...],
    fg_sizes: tuple[int, ...],
    fg: Figaroh | None,
    workdir: Path,
    repeats: int,
    fg_repeats: int,
) -> list[ScaleRow]:
    rows = []
    per_pose: float | None = None  # FIGAROH seconds per pose, from the last size run
    for n in sizes:
        q = random_joints(nominal, rng, n)
        m = measure(cell, q, rng, sigma_mm)
        res = calibrate(nominal, q, m)
        specs = res.covariance_specs
        plain = plain_fit(nominal, q, m, specs)
        plain_rms = float(np.sqrt(np.mean(np.sum((m - plain.predict(q)) ** 2, axis=1))))
        reps = repeats if n <= 1000 else max(1, min(repeats, 3))
        t_cal, t_plain, t_jac = _best_interleaved(
            [
                partial(calibrate, nominal, q, m),
                partial(plain_fit, nominal, q, m, specs, measure_memory=False),
                partial(scipy_with_jacobian, nominal, q, m, specs),
            ],
            reps,
        )
        run: FigarohRun | None = None
        note = ""
        expected = "" if per_pose is None else f", ~{per_pose * n:.0f} s expected"
        if fg is None:
            note = "not installed"
        elif n not in fg_sizes:
            note = f"skipped{expected}"
        elif per_pose is not None and per_pose * n > FIGAROH_BUDGET_S:
            note = f"skipped{expected} > {FIGAROH_BUDGET_S:g} s"
        else:
            try:
                run = run_figaroh(fg, nominal, q, m, workdir, repeats=fg_repeats if n <= 100 else 1)
                per_pose = run.total_s / n
            except Exception as exc:  # the peer failing is a result to print
                note = f"failed: {type(exc).__name__}: {exc}"
        rows.append(
            ScaleRow(
                n=n,
                repeats=reps,
                cellcal_s=t_cal,
                cellcal_bytes=_peak_bytes(partial(calibrate, nominal, q, m)),
                rms_after=res.rms_after,
                plain_s=t_plain,
                plain_bytes=plain.peak_bytes,
                plain_rms=plain_rms,
                jacobian_s=t_jac,
                figaroh=run,
                figaroh_note=note,
            )
        )
    return rows


def print_scaling(rows: list[ScaleRow], robot: str) -> None:
    print()
    print(f"== 4. Scaling: calibration wall time and memory against the number of poses ({robot})")
    print(
        "   plain = scipy least_squares (lm, finite-difference Jacobian) of cellcal's "
        "parameters; scipy + J = the same with cellcal's analytic Jacobian"
    )
    print(
        "    poses  cellcal ms   plain ms  ratio  scipy+J ms  ratio   peak MiB cellcal/plain"
        "   in-sample RMS mm cellcal/plain   FIGAROH s   ratio"
    )
    for r in rows:
        if r.figaroh is not None:
            fig = f"{r.figaroh.total_s:9.2f}  {r.figaroh.total_s / r.cellcal_s:6.0f}×"
        else:
            fig = f"   {r.figaroh_note}"
        print(
            f"   {r.n:6d} {r.cellcal_s * 1e3:11.1f} {r.plain_s * 1e3:10.1f} {r.plain_ratio:5.1f}×"
            f" {r.jacobian_s * 1e3:11.1f} {r.jacobian_s / r.cellcal_s:5.1f}×"
            f"   {r.cellcal_bytes / 2**20:7.2f} / {r.plain_bytes / 2**20:<7.2f}"
            f"        {r.rms_after:.4f} / {r.plain_rms:.4f}         {fig}"
        )
    print(f"   (times: best of {rows[0].repeats} up to 1000 poses, of fewer above; interleaved)")


def speed_verdict(rows: list[ScaleRow]) -> str:
    """The goal against the plain fit, computed from the rows."""
    worst = min(rows, key=lambda r: r.plain_ratio)
    heavier = [r.n for r in rows if r.cellcal_bytes > r.plain_bytes]
    sizes = f"{rows[0].n}–{rows[-1].n}"
    return (
        f"against the plain scipy fit cellcal is {worst.plain_ratio:.1f}× faster at worst "
        f"({worst.n} poses; goal ≥ {PLAIN_SPEED_GOAL:g}× at every size {sizes}: "
        f"{'met' if worst.plain_ratio >= PLAIN_SPEED_GOAL else 'NOT met'}) and needs "
        + (
            "no more memory at any size (met)"
            if not heavier
            else f"more memory at {', '.join(map(str, heavier))} poses (NOT met)"
        )
    )
