"""Section 1 of benchmarks/calibration.py: cellcal against FIGAROH on the same simulated
data — held-out accuracy, time, parameters identified."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from calibration_scenario import (
    N_CALIBRATION,
    N_HELD_OUT,
    SIGMA_MM,
    Accuracy,
    Scenario,
    before_prediction,
    best_of,
    how_timed,
    make_scenario,
)
from figaroh_peer import Figaroh, FigarohRun, run_figaroh
from numpy.typing import NDArray

from cellcal.calib.identification import CalibrationResult, calibrate
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.validation import ErrorStats
from cellcal.files.models import load_model

Array = NDArray[np.float64]
T = TypeVar("T")

# --------------------------------------------------------------------------- 1. versus FIGAROH


@dataclass
class Comparison:
    robot: str
    sc: Scenario
    result: CalibrationResult
    cellcal_s: float
    cellcal_repeats: int
    cellcal: Accuracy
    before: Accuracy
    figaroh: FigarohRun | None = None
    figaroh_acc: Accuracy | None = None
    figaroh_tool: FigarohRun | None = None
    figaroh_tool_acc: Accuracy | None = None
    figaroh_error: str = ""
    fk_agree_mm: float = math.nan
    noise_free_cellcal_mm: float = math.nan
    noise_free_figaroh_mm: float = math.nan
    noise_free_figaroh_val_mm: float = math.nan
    figaroh_train_mm: float = math.nan
    figaroh_tool_train_mm: float = math.nan


def compare(
    robot: str,
    rng: np.random.Generator,
    fg: Figaroh | None,
    workdir: Path,
    repeats: int,
    fg_repeats: int,
) -> Comparison:
    nominal = load_model(robot).model
    sc = make_scenario(nominal, rng, N_CALIBRATION, N_HELD_OUT)
    seconds, result = best_of(lambda: calibrate(nominal, sc.q, sc.measured), repeats)
    cmp = Comparison(
        robot=robot,
        sc=sc,
        result=result,
        cellcal_s=seconds,
        cellcal_repeats=repeats,
        cellcal=Accuracy.of(result.predict(sc.q_val), sc),
        before=Accuracy.of(before_prediction(nominal, sc.q, sc.measured, sc.q_val), sc),
    )
    # Noise-free data: can the model reproduce the truth at all?
    clean = sc.cell.positions(sc.q)
    cmp.noise_free_cellcal_mm = calibrate(nominal, sc.q, clean).rms_after
    if fg is None:
        return cmp
    try:
        run = run_figaroh(fg, nominal, sc.q, sc.measured, workdir, repeats=fg_repeats)
        cmp.figaroh = run
        cmp.figaroh_acc = Accuracy.of(run.predict(sc.q_val), sc)
        cmp.figaroh_train_mm = ErrorStats.of(run.predict(sc.q) - sc.measured).rms
        # The URDF is right: FIGAROH's FK of the nominal model equals cellcal's.
        k = target_kinematics(nominal, sc.q_val, nominal.target_offset, jacobian=False)
        p0 = run.predict(sc.q_val, np.zeros(0), [])
        cmp.fk_agree_mm = float(np.max(np.abs(p0 - k.p)))
        tool_run = run_figaroh(
            fg, nominal, sc.q, sc.measured, workdir, urdf_tool=sc.cell.target_offset, repeats=1
        )
        cmp.figaroh_tool = tool_run
        cmp.figaroh_tool_acc = Accuracy.of(tool_run.predict(sc.q_val), sc)
        cmp.figaroh_tool_train_mm = ErrorStats.of(tool_run.predict(sc.q) - sc.measured).rms
        nf = run_figaroh(fg, nominal, sc.q, clean, workdir, repeats=1)
        cmp.noise_free_figaroh_mm = ErrorStats.of(nf.predict(sc.q) - clean).rms
        cmp.noise_free_figaroh_val_mm = ErrorStats.of(nf.predict(sc.q_val) - sc.truth_val).rms
    except Exception as exc:  # the peer failing is a result to print, not a crash
        cmp.figaroh_error = f"{type(exc).__name__}: {exc}"
    return cmp


def _acc_cells(a: Accuracy) -> str:
    t, m = a.truth, a.measured
    return f"{t.rms:8.4f} {t.mean:8.4f} {t.max:8.4f}   {m.rms:8.4f} {m.mean:8.4f} {m.max:8.4f}"


def print_comparison(c: Comparison, fg: Figaroh | None) -> None:
    sc = c.sc
    dist = float(np.linalg.norm(sc.cell.T_sensor_base[:3, 3]))
    print(
        f"   {c.robot}: sensor {dist / 1000:.2f} m from the base, target offset "
        f"({', '.join(f'{v:g}' for v in sc.cell.target_offset)}) mm unknown (nominal "
        f"({', '.join(f'{v:g}' for v in sc.nominal.target_offset_xyz)}))"
    )
    print(
        "                                  params   time [ms]      held-out vs truth [mm]"
        "          vs measured [mm]"
    )
    print(
        "                                                          RMS     mean      max"
        "        RMS     mean      max"
    )
    print(f"   before (nominal + frames)          —          —    {_acc_cells(c.before)}")
    n_cc = len(c.result.identifiability.identified)
    print(
        f"   cellcal                         {n_cc:5d} {c.cellcal_s * 1e3:10.1f}    "
        f"{_acc_cells(c.cellcal)}"
    )
    f = c.figaroh
    ft = c.figaroh_tool
    if fg is not None and f is not None and c.figaroh_acc is not None:
        print(
            f"   FIGAROH {fg.version:24s}{len(f.names):5d} {f.total_s * 1e3:10.1f}    "
            f"{_acc_cells(c.figaroh_acc)}"
        )
        if ft is not None and c.figaroh_tool_acc is not None:
            print(
                f"   FIGAROH, true offset in URDF    {len(ft.names):5d} "
                f"{ft.total_s * 1e3:10.1f}    {_acc_cells(c.figaroh_tool_acc)}"
            )
    print(
        f"   cellcal: {how_timed(c.cellcal_repeats)} of calibrate(); {c.result.evaluations} "
        f"evaluations; condition number {c.result.condition_number:.1f}; unidentifiable: "
        f"{', '.join(c.result.unidentifiable)}"
    )
    if fg is None:
        return
    if f is None or c.figaroh_acc is None:
        print(f"   FIGAROH failed: {c.figaroh_error}")
        return
    print(
        f"   FIGAROH: {how_timed(f.repeats)} of load URDF+config {f.load_s * 1e3:.0f} ms + "
        f"initialize {f.init_s * 1e3:.0f} ms + solve {f.solve_s * 1e3:.0f} ms (import "
        f"{fg.import_s:.2f} s and file writing excluded); LM success={f.success}, nfev={f.nfev},"
        f" {f.n_evals} residual evaluations (finite-difference Jacobian)"
    )
    print(f"            absorbed by the frames: {', '.join(f.absorbed) or 'none'}")
    print(
        f"   in-sample RMS: cellcal {c.result.rms_after:.4f} mm, FIGAROH "
        f"{c.figaroh_train_mm:.4f} mm (σ√3 = {SIGMA_MM * math.sqrt(3):.4f} mm)"
    )
    if ft is not None:
        kin = [n for n in f.names if n.startswith("d_")]
        kin_t = [n for n in ft.names if n.startswith("d_")]
        print(
            f"   FIGAROH with the true target offset written into its URDF (nominal offset "
            f"otherwise): {len(ft.names)} parameters, absorbed: {', '.join(ft.absorbed) or 'none'}"
        )
        print(
            f"            joint parameters lost against the run above: "
            f"{', '.join(n for n in kin if n not in kin_t) or 'none'}; gained: "
            f"{', '.join(n for n in kin_t if n not in kin) or 'none'}; in-sample RMS "
            f"{c.figaroh_tool_train_mm:.4f} mm"
        )
        print(
            f"            structural rows renamed to base_*: {', '.join(ft.renamed_base)} (run "
            f"above: {', '.join(f.renamed_base)})"
        )
    print(
        f"   URDF check: FIGAROH's FK of the nominal URDF vs cellcal's FK, max diff "
        f"{c.fk_agree_mm:.1e} mm"
    )
    print(
        f"   noise-free data (model check): in-sample RMS cellcal {c.noise_free_cellcal_mm:.1e} "
        f"mm, FIGAROH {c.noise_free_figaroh_mm:.4f} mm (held-out vs truth "
        f"{c.noise_free_figaroh_val_mm:.4f} mm)"
    )
    t_ratio = f.total_s / c.cellcal_s
    e_ratio = c.figaroh_acc.truth.rms / c.cellcal.truth.rms
    print(
        f"   ratio FIGAROH / cellcal: time {t_ratio:.1f}× (solve alone "
        f"{f.solve_s / c.cellcal_s:.1f}×), held-out RMS vs truth {e_ratio:.2f}×, vs measured "
        f"{c.figaroh_acc.measured.rms / c.cellcal.measured.rms:.2f}×"
    )
