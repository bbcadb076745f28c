"""Real robots' public laser-tracker data (tests/data/real, MIT): cellcal's calibration
against the nominal model with best-fit frames and against the exact-rank selection
alone (what cellcal did before identifiability became a matter of degree), measured
in the same run on the source's separate test poses."""

from __future__ import annotations

import time
from pathlib import Path

import cellcal.calib.identification as identification
from cellcal.calib.identification import CalibrationResult, calibrate
from cellcal.calib.validation import Validation, validate_on
from cellcal.measurementfiles import read_measurements
from cellcal.modelfiles import load_model

REAL = Path(__file__).parents[1] / "tests" / "data" / "real"


def _largest(res: CalibrationResult) -> str:
    kin = [p for p in res.parameters if p.identified and p.kind != "tool"]
    mm = max(kin, key=lambda p: abs(p.value) if p.unit == "mm" else 0.0)
    deg = max(kin, key=lambda p: abs(p.value) if p.unit == "deg" else 0.0)
    return f"{mm.name} {mm.value:+.2f} mm, {deg.name} {deg.value:+.2f}°"


def _run(robot: str, *, exact_rank: bool) -> tuple[CalibrationResult, Validation, float]:
    nominal = load_model(str(REAL / robot / "model.toml")).model
    data = read_measurements(REAL / robot / "measurements.csv", nominal.dof)
    val = read_measurements(REAL / robot / "validation.csv", nominal.dof)
    saved = identification.weakly_determined
    if exact_rank:
        identification.weakly_determined = lambda J, s, ident: ident  # type: ignore[assignment]
    try:
        t0 = time.perf_counter()
        res = calibrate(nominal, data.q, data.xyz, accept=True)
        seconds = time.perf_counter() - t0
    finally:
        identification.weakly_determined = saved  # type: ignore[assignment]
    return res, validate_on(res, data.q, data.xyz, val.q, val.xyz), seconds


def print_real() -> None:
    print()
    print("== 6. Real robots (public laser-tracker data, held-out test poses of the source)")
    print(
        "   robot          poses  held-out RMS mm: nominal  cellcal  exact-rank  "
        "ratio  | largest corrections (cellcal / exact-rank)"
    )
    for robot in ("ur5", "barrett-wam"):
        res, v, s = _run(robot, exact_rank=False)
        old, vo, _ = _run(robot, exact_rank=True)
        print(
            f"   {robot:<14}{res.n_points:>6}  {v.before.rms:>22.4f}{v.after.rms:>9.4f}"
            f"{vo.after.rms:>12.4f}{v.after.rms / vo.after.rms:>7.2f}  | "
            f"{_largest(res)} / {_largest(old)}"
        )
        weak = [p.name for p in res.parameters if p.at_nominal == "weak"]
        print(
            f"   {'':<14}hidden by the noise, left at nominal: {', '.join(weak) or 'none'}; "
            f"calibrate() {s * 1e3:.0f} ms"
        )
