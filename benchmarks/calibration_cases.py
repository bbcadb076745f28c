"""Sections 2 and 3 of benchmarks/calibration.py: the noise-limited bound (first-order
held-out error against the measured one) and the paper's 200 mm cube at one flange
orientation against the same cube with the wrist varied."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from calibration_scenario import (
    BOUND_TARGET,
    CUBE_CENTRE_MM,
    CUBE_GRID,
    CUBE_MM,
    CUBE_SEED_DEG,
    IMPROVEMENT_TARGET,
    PAPER_CL_MM,
    PAPER_OTHER_MM,
    PAPER_OUTSIDE_MM,
    SIGMA_MM,
    TOOL_MM,
    WRIST_SPREAD_DEG,
    met,
)
from calibration_versus import Comparison
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.calib.error_model import State, jacobian, predict
from cellcal.calib.identification import CalibrationResult, calibrate, fit_frames
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.validation import ErrorStats
from cellcal.mocks.robot_truth import measure

Array = NDArray[np.float64]
T = TypeVar("T")

# --------------------------------------------------------------------------- 2. bound


@dataclass(frozen=True)
class Bound:
    bound_mm: float
    bound_origin_mm: float  # with the frame rotation about the sensor origin
    std_agree: float  # max relative diff of cellcal's std·σ/σ₀ and √diag C
    sigma0_ratio: float
    measured_mm: float
    mc_rms_mm: float
    mc_draws: int
    figaroh_mm: float
    before_mm: float


def bound_sq(
    state: State, result: CalibrationResult, q: Array, q_val: Array
) -> tuple[Array, Array]:
    """Per held-out pose E|δp|² for the true σ, and C (internal units)."""
    ident = result.identifiability
    specs = tuple(ident.specs[i] for i in ident.identified)
    _, J = jacobian(state, q, specs)
    J2 = J.reshape(-1, len(specs))
    norms = np.linalg.norm(J2, axis=0)
    Js = J2 / norms
    C = SIGMA_MM**2 * np.linalg.inv(Js.T @ Js) / np.outer(norms, norms)
    _, Jv = jacobian(state, q_val, specs)
    out: Array = np.einsum("nia,ab,nib->n", Jv, C, Jv)
    return out, C


def noise_bound(c: Comparison, rng: np.random.Generator, draws: int) -> Bound:
    sc, res = c.sc, c.result
    # calibrate() turns the sensor frame about the measurements' centroid.
    T_ib = res.T_sensor_base
    pivot = State(
        res.calibrated, res.target_offset, T_ib[:3, :3], T_ib[:3, 3], sc.measured.mean(axis=0)
    )
    b2, C = bound_sq(pivot, res, sc.q, sc.q_val)
    b2_origin, _ = bound_sq(res.state, res, sc.q, sc.q_val)
    # cellcal's reported standard uncertainties, rescaled from σ₀ to σ, against √diag C.
    ident = res.identifiability
    col = {ident.specs[i].name: k for k, i in enumerate(ident.identified)}
    rel = []
    for p in res.parameters:
        if p.identified:
            spec = ident.specs[ident.identified[col[p.name]]]
            ref = spec.to_display(math.sqrt(C[col[p.name], col[p.name]]))
            rel.append(abs(p.std * SIGMA_MM / res.sigma0 - ref) / ref)
    # Monte Carlo: the same poses and robot, fresh noise.
    sq = []
    for _ in range(draws):
        m = measure(sc.cell, sc.q, rng, SIGMA_MM)
        r = calibrate(sc.nominal, sc.q, m)
        e = r.predict(sc.q_val) - sc.truth_val
        sq.append(float(np.mean(np.sum(e * e, axis=1))))
    return Bound(
        bound_mm=float(np.sqrt(np.mean(b2))),
        bound_origin_mm=float(np.sqrt(np.mean(b2_origin))),
        std_agree=max(rel) if rel else math.nan,
        sigma0_ratio=res.sigma0 / SIGMA_MM,
        measured_mm=c.cellcal.truth.rms,
        mc_rms_mm=float(np.sqrt(np.mean(sq))) if sq else math.nan,
        mc_draws=draws,
        figaroh_mm=c.figaroh_acc.truth.rms if c.figaroh_acc else math.nan,
        before_mm=c.before.truth.rms,
    )


def print_bound(c: Comparison, b: Bound) -> None:
    print()
    print(
        f"== 2. Noise-limited bound ({c.robot}, {len(c.sc.q)} poses, σ = {SIGMA_MM:g} mm per axis)"
    )
    print(
        "   E|δp|² = trace(J(x) C J(x)ᵀ), C = σ²(JᵀJ)⁻¹ over the "
        f"{len(c.result.identifiability.identified)} identified parameters, J at the solution"
    )
    print(
        f"   first-order RMS bound at the {len(c.sc.q_val)} held-out poses: "
        f"{b.bound_mm:.5f} mm (frame turning about the measurements' centroid, as calibrate)"
    )
    rel = abs(b.bound_origin_mm - b.bound_mm) / b.bound_mm
    print(
        f"   the same with the frame turning about the sensor origin (result.state): "
        f"{b.bound_origin_mm:.5f} mm, relative difference {rel:.1e} (a reparameterisation)"
    )
    print(
        f"   cellcal's reported std × σ/σ₀ vs √diag C: max relative difference "
        f"{b.std_agree:.1e}; σ₀/σ = {b.sigma0_ratio:.3f}"
    )
    r1 = b.measured_mm / b.bound_mm
    r_mc = b.mc_rms_mm / b.bound_mm
    print(
        f"   held-out RMS vs truth / bound: cellcal {r1:.2f}× (this draw, {b.measured_mm:.5f} mm),"
        f" {r_mc:.2f}× (RMS over {b.mc_draws} fresh noise draws, {b.mc_rms_mm:.5f} mm)"
        f"   (target ≤ {BOUND_TARGET:g}×: {met(max(r1, r_mc) <= BOUND_TARGET)})"
    )
    if math.isfinite(b.figaroh_mm):
        print(f"                                  FIGAROH {b.figaroh_mm / b.bound_mm:.2f}×")
    imp = b.before_mm / b.measured_mm
    print(
        f"   held-out RMS before / after: {b.before_mm:.4f} → {b.measured_mm:.5f} mm = {imp:.0f}×"
        f"   (target ≥ {IMPROVEMENT_TARGET:g}×: {met(imp >= IMPROVEMENT_TARGET)})"
    )
    print(
        f"   the paper (real robot, other method vs CL, not before/after): {PAPER_OTHER_MM} → "
        f"{PAPER_CL_MM} mm = {PAPER_OTHER_MM / PAPER_CL_MM:.2f}×"
    )


# --------------------------------------------------------------------------- 3. the cube


@dataclass(frozen=True)
class CubeCase:
    label: str
    n_ok: int
    n_val_ok: int
    result: CalibrationResult
    inside_before: ErrorStats
    inside_after: ErrorStats
    outside_before: ErrorStats
    outside_after: ErrorStats


def cube_points() -> Array:
    axes = [np.linspace(-CUBE_MM / 2, CUBE_MM / 2, k) for k in CUBE_GRID]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    out: Array = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]) + np.asarray(CUBE_CENTRE_MM)
    return out


def orientations(R0: Array, n: int, varied: bool, rng: np.random.Generator) -> Array:
    if not varied:
        return np.broadcast_to(R0, (n, 3, 3)).copy()
    tilt = Rotation.from_euler(
        "xyz", rng.uniform(-WRIST_SPREAD_DEG, WRIST_SPREAD_DEG, (n, 3)), degrees=True
    )
    out: Array = R0 @ tilt.as_matrix()  # about the flange's own axes
    return out


def cube_case(
    label: str, varied: bool, c: Comparison, rng: np.random.Generator, n_val: int
) -> CubeCase:
    sc = c.sc
    nominal = sc.nominal
    target_offset = np.asarray(TOOL_MM)
    q_seed = np.radians(CUBE_SEED_DEG)
    R0 = target_kinematics(nominal, q_seed[None], target_offset, jacobian=False).R_flange[0]
    P = cube_points()
    ik = solve(nominal, target_offset, P, orientations(R0, len(P), varied, rng), q_seed)
    q = ik.q[ik.ok]
    m = measure(sc.cell, q, rng, SIGMA_MM)
    result = calibrate(nominal, q, m)
    base = fit_frames(nominal, q, m)
    Pv = rng.uniform(-CUBE_MM / 2, CUBE_MM / 2, (n_val, 3)) + np.asarray(CUBE_CENTRE_MM)
    ikv = solve(nominal, target_offset, Pv, orientations(R0, n_val, varied, rng), q_seed)
    qv = ikv.q[ikv.ok]
    truth = sc.cell.positions(qv)
    return CubeCase(
        label=label,
        n_ok=int(ik.ok.sum()),
        n_val_ok=int(ikv.ok.sum()),
        result=result,
        inside_before=ErrorStats.of(predict(base, qv) - truth),
        inside_after=ErrorStats.of(result.predict(qv) - truth),
        outside_before=ErrorStats.of(predict(base, sc.q_val) - sc.truth_val),
        outside_after=ErrorStats.of(result.predict(sc.q_val) - sc.truth_val),
    )


def print_cube(cases: list[CubeCase], c: Comparison, n_val: int) -> None:
    print()
    g = "×".join(str(k) for k in CUBE_GRID)
    print(
        f"== 3. The paper's case: {g} grid filling a {CUBE_MM:g} mm cube centred at "
        f"({', '.join(f'{v:g}' for v in CUBE_CENTRE_MM)}) mm, {c.robot}, σ = {SIGMA_MM:g} mm"
    )
    print(
        f"   IK on the nominal model, target offset ({', '.join(f'{v:g}' for v in TOOL_MM)}) mm,"
        f" seed q = ({', '.join(f'{v:g}' for v in CUBE_SEED_DEG)})°, orientation of the seed;"
    )
    print(
        f"   'varied': each point's flange turned by up to ±{WRIST_SPREAD_DEG:g}° about each "
        f"flange axis. Held-out: {n_val} random points in the cube, same kind of orientation;"
    )
    print(
        f"   'outside': the {len(c.sc.q_val)} well-spread held-out poses of section 1. "
        "Errors against the noise-free truth, RMS in mm."
    )
    for k in cases:
        r = k.result
        print(
            f"   {k.label:18s} poses {k.n_ok}/{len(cube_points())} (held-out {k.n_val_ok}/{n_val}),"
            f" condition number {r.condition_number:.3g}, identified "
            f"{len(r.identifiability.identified)} (incl. 6 frame)"
        )
        print(f"      unidentifiable: {', '.join(r.unidentifiable) or 'none'}")
        print(
            f"      in-sample {r.rms_before:.4f} → {r.rms_after:.4f}; held-out in the cube "
            f"{k.inside_before.rms:.4f} → {k.inside_after.rms:.4f} "
            f"({k.inside_before.rms / k.inside_after.rms:.1f}×); outside "
            f"{k.outside_before.rms:.4f} → {k.outside_after.rms:.4f} "
            f"({k.outside_before.rms / k.outside_after.rms:.1f}×)"
        )
        for w in r.warnings:
            print(f"      warning: {w}")
    print(
        f"   the paper: after calibration {PAPER_CL_MM} mm (CL) vs {PAPER_OTHER_MM} mm (other "
        f"method) in the region, {PAPER_OUTSIDE_MM} mm outside it"
    )
