"""``cellcal calibrate``: identify kinematic errors and write the calibrated model."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import click
import numpy as np

from cellcal.calib.error_terms import term_to_dict
from cellcal.calib.geometry import so3_log
from cellcal.calib.identification import (
    ROBUST_LOSSES,
    CalibrationResult,
)
from cellcal.calib.identification import (
    calibrate as run_calibration,
)
from cellcal.calib.observations import on_a_line
from cellcal.calib.outliers import OUTLIER_Z, PointResidual, point_residuals
from cellcal.calib.parameter_choice import FOLDS
from cellcal.calib.term_choice import FIXED, TermRequest, parse_terms
from cellcal.calib.validation import (
    Validation,
    cross_validate,
    held_out_groups,
    validate_on,
)
from cellcal.commands.output import SEED, print_json, warn
from cellcal.commands.terms_output import terms_lines
from cellcal.errors import AcceptanceError, InputError, UserError
from cellcal.files.measurements import Measurements, read_measurements
from cellcal.files.models import builtin_models, load_model, write_calibrated
from cellcal.files.outputs import check_output_file

#: The paper's figures (Liu et al. 2018, Sec. 4.2): position error after calibration with
#: another registration method (0.436) and with its own (0.200), and outside the region.
PAPER_BEFORE_MM, PAPER_AFTER_MM, PAPER_OUTSIDE_MM = 0.436, 0.200, 0.323


def _stats(v: Validation, which: str) -> dict[str, float]:
    s = getattr(v, which)
    return {"mean_mm": s.mean, "rms_mm": s.rms, "max_mm": s.max, "p95_mm": s.p95, "n": s.n}


def at_nominal_text(res: CalibrationResult) -> str:
    """Parameters left at nominal, grouped by why."""
    why = {"rank": "not identifiable", "weak": "hidden by the noise", "fixed": "fixed"}
    parts = []
    for reason, label in why.items():
        names = [p.name for p in res.parameters if p.at_nominal == reason]
        if names:
            parts.append(f"{', '.join(names)} ({label})")
    return "; ".join(parts) or "none"


def choice_text(res: CalibrationResult) -> str | None:
    """How the k-fold held-out error chose among the noise-hidden parameters."""
    c = res.parameter_choice
    if c is None:
        return None
    freed = ", ".join(c.freed) if c.freed else "none"
    line = (
        f"{FOLDS}-fold held-out error of the noise-hidden parameters' choice: "
        f"{c.rule_mm:.4g} left out, {c.chosen_mm:.4g} chosen (freed: {freed})"
    )
    if c.tempting:
        line += "; lower but beyond tolerance: " + ", ".join(
            f"{n} {cv:.4g}" for n, cv in c.tempting
        )
    return line


def echo_points(points: tuple[PointResidual, ...], title: str) -> None:
    """The per-point table: name, residual vector, length, robust z, flag (mm)."""
    width = max([len(p.name) for p in points] + [5])
    click.echo(f"{title} (mm; z: robust z-score, outliers above {OUTLIER_Z:g}):")
    click.echo(f"  {'point':<{width}}{'dx':>11}{'dy':>11}{'dz':>11}{'|e|':>11}{'z':>7}")
    for p in points:
        flag = "  outlier" if p.outlier else ""
        click.echo(
            f"  {p.name:<{width}}{p.dx:11.4f}{p.dy:11.4f}{p.dz:11.4f}{p.error:11.4f}"
            f"{p.z:7.1f}{flag}"
        )


def _report(
    res: CalibrationResult,
    v: Validation | None,
    data_path: str,
    points: tuple[PointResidual, ...],
) -> None:
    m = res.nominal
    click.echo(f"calibrate: {m.name} ({m.convention}), {res.n_points} points from {data_path}")
    n_all = len(res.parameters)
    click.echo(
        f"identified {len(res.identified)} of {n_all} parameters, plus the sensor frame; "
        f"left at nominal: {at_nominal_text(res)}"
    )
    chosen = choice_text(res)
    if chosen is not None:
        click.echo(chosen)
    line = f"condition number {res.condition_number:.3g}"
    equal = res.condition_number_equal_weights
    if res.weighted and math.isfinite(equal):
        line += f" weighted by sx,sy,sz ({equal:.4g} with equal weights, `plan`'s measure)"
    if res.identifiability.correlated:
        pairs = ", ".join(f"{a}–{b} (ρ {r:+.3f})" for a, b, r in res.identifiability.correlated)
        line += f"; strongly correlated: {pairs}"
    click.echo(line)
    click.echo(
        f"fit: RMS before {res.rms_before:.4f} mm, after {res.rms_after:.4f} mm, "
        f"max after {res.max_after:.4f} mm; σ₀ {res.sigma0:.4g} (dof {res.dof})"
        + ("; weighted by sx,sy,sz" if res.weighted else "")
    )
    if v is not None:
        click.echo(f"validation ({v.method}, {v.after.n} held-out points), position error in mm:")
        click.echo(f"  {'':<7}{'mean':>11}{'RMS':>11}{'max':>11}{'p95':>11}")
        for label, s in (("before", v.before), ("after", v.after)):
            click.echo(f"  {label:<7}{s.mean:11.4f}{s.rms:11.4f}{s.max:11.4f}{s.p95:11.4f}")
        pct = 100.0 * (1.0 - v.after.rms / v.before.rms)
        change = (
            f"{v.improvement:.1f}× lower ({pct:.1f} % reduction)"
            if v.after.rms <= v.before.rms
            else f"{1.0 / v.improvement:.2f}× HIGHER ({-pct:.1f} % worse than before)"
        )
        click.echo(
            f"  held-out RMS {change}; the paper, "
            f"after calibration: {PAPER_AFTER_MM:.3f} mm with its registration vs "
            f"{PAPER_BEFORE_MM:.3f} mm with another ({PAPER_BEFORE_MM / PAPER_AFTER_MM:.2f}×, "
            'printed as "45.8 %")'
        )
    if res.orientation_residuals is not None:
        o = np.degrees(np.linalg.norm(res.orientation_residuals, axis=1))
        click.echo(
            f"orientation (6-DOF): RMS after {float(np.sqrt(np.mean(o * o))):.5f}°, "
            f"max {float(o.max()):.5f}°"
        )
    click.echo(
        "parameters (correction to nominal ± 1σ; target offset and orientation as estimated):"
    )
    width = max([len(p.name) for p in res.parameters] + [6]) + 2
    for p in res.parameters:
        if p.identified:
            click.echo(f"  {p.name:<{width}}{p.value:+13.5f} ± {p.std:.5f} {p.unit}")
    for text in terms_lines(res):
        click.echo(text)
    echo_points(points, "per-point residuals after the fit")
    frames = res.frames if res.frames is not None else res.T_sensor_base[None]
    stds = res.frames_std if res.frames_std is not None else res.frame_std[None]
    for name, T, sd in zip(res.sessions, frames, stds, strict=True):
        rv = np.degrees(so3_log(T[:3, :3]))
        label = f" of session {name}" if name else ""
        click.echo(
            f"sensor frame{label} T_sensor_base: rotation vector ({rv[0]:.5f}, "
            f"{rv[1]:.5f}, {rv[2]:.5f})° ± ({', '.join(f'{v:.2g}' for v in np.degrees(sd[:3]))})°, "
            f"translation ({T[0, 3]:.4f}, {T[1, 3]:.4f}, {T[2, 3]:.4f}) mm ± "
            f"({', '.join(f'{v:.2g}' for v in sd[3:])}) mm"
        )


def _sessions_off_a_line(data: Measurements) -> Measurements:
    """The data less each session whose points lie on a line, said in one line each:
    such a session cannot fix its sensor frame (the rotation about the line), and fitted
    with the others it spoils their fit. Alone, or when every session does, the
    calibration refuses it (exit 2)."""
    g = data.groups
    if len(g.sessions) < 2:
        return data
    keep = np.ones(len(data.q), dtype=bool)
    said: list[str] = []
    for s, name in enumerate(g.sessions):
        rows = g.session == s
        line = on_a_line(data.xyz[rows])
        if line is not None:
            keep &= ~rows
            said.append(
                f"session {name!r} left out of the fit: {line.reason()}; the other sessions "
                "are fitted (measure it again with poses off the line)"
            )
    if keep.all() or not keep.any():
        return data
    for line_said in said:
        warn(line_said)

    def rows_of(labels: tuple[str, ...] | None) -> tuple[str, ...] | None:
        return None if labels is None else tuple(np.asarray(labels, dtype=object)[keep])

    return replace(
        data,
        names=tuple(np.asarray(data.names, dtype=object)[keep]),
        q=data.q[keep],
        xyz=data.xyz[keep],
        sigma=None if data.sigma is None else data.sigma[keep],
        targets=rows_of(data.targets),
        sessions=rows_of(data.sessions),
        orientations=None if data.orientations is None else data.orientations[keep],
        conditions=None
        if data.conditions is None
        else data.conditions.subset(np.flatnonzero(keep)),
    )


@click.command()
@click.option(
    "--model",
    "model_spec",
    required=True,
    help="Built-in name (see `cellcal models`) or TOML file.",
)
@click.option(
    "--data",
    "data_path",
    required=True,
    help="CSV q1..qN,x,y,z (deg, mm); optional columns name, sx,sy,sz (1σ), target (one "
    "offset per target), session (one sensor frame per set-up), ori_w..ori_z (6-DOF), "
    "time_s, temperature_c, payload_kg (for error terms beyond geometry).",
)
@click.option("--out", "out_path", help="Write the calibrated model (TOML) here.")
@click.option(
    "--validate", "validate_path", help="Held-out measurements (same format) to validate on."
)
@click.option(
    "--folds",
    type=int,
    default=5,
    show_default=True,
    help="k-fold cross-validation when no --validate file (0: none).",
)
@click.option(
    "--robust", type=click.Choice(ROBUST_LOSSES), help="Robust loss after the least-squares fit."
)
@click.option(
    "--paper-parameters", is_flag=True, help="The paper's θ, d, a, α on every row (no Hayati β)."
)
@click.option(
    "--fix",
    "fix",
    help="Parameters to keep at nominal, comma-separated (e.g. alpha5,a5); 'kinematics' "
    "holds the whole geometry (re-registers a new set-up with a calibrated --model), "
    "'target_offset' the target offset.",
)
@click.option(
    "--accept",
    is_flag=True,
    help="Write the model even if an acceptance check fails (the failures are recorded).",
)
@click.option(
    "--terms",
    default="auto",
    show_default=True,
    help="Error terms beyond geometry: auto (each added only when blocked cross-validation "
    "accepts it), geometric (none), or a comma list of gravity, compliance, harmonics, "
    "drift (fitted without the gate; the cross-validation still reported).",
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the k-fold split.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def calibrate(
    model_spec: str,
    data_path: str,
    out_path: str | None,
    validate_path: str | None,
    folds: int,
    robust: str | None,
    paper_parameters: bool,
    fix: str | None,
    accept: bool,
    terms: str,
    seed: int,
    as_json: bool,
) -> None:
    """Identify the kinematic errors from measured target positions.

    The model (--model) is a built-in name or a TOML file of revolute joints (standard
    or modified DH, any number of joints, per joint an optional scale (-1: a reversed
    axis) and couple = { joint = J, factor = F } (e.g. FANUC's J2/J3 coupling)); a
    calibrated model written by --out is accepted too, e.g. with --fix kinematics to
    re-register a new set-up. Several targets (a target column) each get their own
    offset, several sessions (a session column) their own sensor frame, and 6-DOF
    measurements (ori_w..ori_z) are fitted in orientation too. A result that
    fails an acceptance check (the target does not follow the robot, units that do not
    fit, corrections beyond manufacturing tolerances, no convergence) exits 3 and writes
    nothing unless --accept is given.
    """
    if folds and folds < 2:
        raise InputError("--folds must be 0 (no validation) or at least 2")
    if out_path is not None:
        check_output_file(out_path)  # before the fit: a device or FIFO is refused at once
    loaded = load_model(model_spec)
    x, y, z = (float(v) for v in loaded.target_offset)
    nominal = replace(loaded.model, target_offset_xyz=(x, y, z))
    pinned = tuple(n.strip() for n in (fix or "").split(",") if n.strip())
    parse_terms(terms)  # a misspelt term is refused before the data are read
    data = _sessions_off_a_line(read_measurements(data_path, nominal.dof))
    alternatives = builtin_models()
    # The calibration and its k-fold folds are made with the same options.
    options: dict[str, Any] = {
        "robust": robust,
        "paper_parameters": paper_parameters,
        "fix": pinned,
        "groups": data.groups,
        "orientations": data.orientations,
        "terms": terms,
        "conditions": data.conditions,
    }
    res = run_calibration(
        nominal, data.q, data.xyz, data.sigma, accept=accept, alternatives=alternatives, **options
    )
    validation: Validation | None = None
    if validate_path is not None:
        val = read_measurements(validate_path, nominal.dof)
        held = held_out_groups(res, len(val.q), val.targets, val.sessions)
        validation = validate_on(
            res, data.q, data.xyz, val.q, val.xyz, data.sigma, held, val.conditions
        )
    elif folds:
        # each fold refits the terms the calibration accepted (choosing them again in
        # every fold would cost five term choices for the same answer)
        chosen = () if res.term_choice is None else res.term_choice.accepted
        options["terms"] = TermRequest(FIXED, chosen) if chosen else "geometric"
        try:
            validation = cross_validate(
                nominal, data.q, data.xyz, data.sigma, folds=folds, seed=seed, **options
            )
        except (UserError, AcceptanceError) as exc:
            warn(f"k-fold validation skipped: {exc}")
    points = point_residuals(data.names, res.residuals)
    for w in res.warnings:
        warn(w)
    if out_path is not None:
        write_calibrated(out_path, res, validation, data_path, points)
    if as_json:
        doc: dict[str, Any] = {
            "n_points": res.n_points,
            "rms_before_mm": res.rms_before,
            "rms_after_mm": res.rms_after,
            "max_after_mm": res.max_after,
            "condition_number": res.condition_number,
            "condition_number_equal_weights": (
                equal if math.isfinite(equal := res.condition_number_equal_weights) else None
            ),
            "identified": list(res.identified),
            "unidentifiable": list(res.unidentifiable),
            "correlated": [list(c) for c in res.identifiability.correlated],
            "sigma0": res.sigma0,
            "dof": res.dof,
            "parameters": [
                {
                    "name": p.name,
                    "unit": p.unit,
                    "identified": p.identified,
                    "value": p.value,
                    "std": p.std,
                }
                for p in res.parameters
            ],
            "target_offset_mm": res.target_offset,
            "T_sensor_base": res.T_sensor_base,
            "targets": {
                name: xyz
                for name, xyz in zip(
                    res.targets,
                    res.target_offsets if res.target_offsets is not None else [res.target_offset],
                    strict=True,
                )
            },
            "sessions": {
                name: T
                for name, T in zip(
                    res.sessions,
                    res.frames if res.frames is not None else [res.T_sensor_base],
                    strict=True,
                )
            },
            "orientation_rms_deg": None
            if res.orientation_residuals is None
            else float(np.degrees(np.sqrt(np.mean(np.sum(res.orientation_residuals**2, axis=1))))),
            "validation": None
            if validation is None
            else {
                "method": validation.method,
                "before": _stats(validation, "before"),
                "after": _stats(validation, "after"),
                "improvement": validation.improvement,
            },
            "paper": {
                "before_mm": PAPER_BEFORE_MM,
                "after_mm": PAPER_AFTER_MM,
                "outside_mm": PAPER_OUTSIDE_MM,
            },
            "at_nominal": {p.name: p.at_nominal for p in res.parameters if not p.identified},
            "parameter_choice": None
            if res.parameter_choice is None
            else {
                "folds": FOLDS,
                "rule_mm": res.parameter_choice.rule_mm,
                "chosen_mm": res.parameter_choice.chosen_mm,
                "freed": list(res.parameter_choice.freed),
                "tried": [
                    {"name": n, "kfold_mm": cv, "plausible": ok}
                    for n, cv, ok in res.parameter_choice.tried
                ],
            },
            "terms": None
            if res.term_choice is None
            else {"accepted": list(res.term_choice.accepted), "rejected": res.term_choice.rejected},
            "blocked_cv_mm": None
            if res.term_choice is None
            else {
                "geometric": res.term_choice.geometric_cv_mm,
                "final": res.term_choice.final_cv_mm,
            },
            "error_terms": [term_to_dict(t) for t in res.calibrated.terms],
            "points": [p.as_dict() for p in points],
            "outliers": [p.name for p in points if p.outlier],
            "warnings": list(res.warnings),
            "out": out_path,
        }
        print_json(doc)
    else:
        _report(res, validation, data_path, points)
        if out_path is not None:
            click.echo(f"wrote {out_path}")
