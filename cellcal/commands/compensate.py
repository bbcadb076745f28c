"""``cellcal compensate``: joint targets from a calibrated model for intended points."""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from cellcal.calib.compensation import (
    BASE,
    FAR,
    LIMITS,
    MAX_CORRECTION_MM,
    REACHED,
    UNREACHED,
    Compensation,
    compensate,
)
from cellcal.calib.geometry import Array, apply, invert, so3_log
from cellcal.calib.kinematics import flange_transforms
from cellcal.calib.robot_model import model_from_dict, require_limits
from cellcal.commands.output import print_json
from cellcal.errors import AcceptanceError, FileFormatError, InputError
from cellcal.files.models import LoadedModel, load_model, write_atomically
from cellcal.files.outputs import check_output_file
from cellcal.files.targets import Targets, read_targets
from cellcal.files.text import read_text, read_toml
from cellcal.store.schema import model_digest

#: How many failed targets a refusal names.
NAMED = 5
#: The acceptance check an answer that cannot be right fails (exit 3), and what usually
#: causes each kind of it.
CHECK = "compensation"
CAUSE = {
    LIMITS: "the point is beyond the robot's joint range in the configuration the seed "
    "picks: give the program's joints (q1..qn columns) or --seed-deg in the "
    "configuration the robot uses there",
    BASE: "the point is at the robot's base, or the seed folds the arm onto it: check the "
    "points' frame (--frame) and give the program's joints (q1..qn columns)",
    FAR: "the calibrated model is not a small correction of the nominal one (a model of "
    f"another robot, an edited file; corrections are a few tenths of a mm, at most "
    f"{MAX_CORRECTION_MM:g} mm), or the seed picks another configuration than the "
    "nominal solution's",
}


def _nominal(loaded: LoadedModel) -> LoadedModel:
    """The controller's model: the nominal geometry the calibrated file records."""
    data = read_toml(Path(loaded.source), label=loaded.source)
    try:
        model = model_from_dict(data["nominal"], f"{loaded.source} [nominal]")
    except KeyError:
        raise FileFormatError(f"{loaded.source}: the calibrated model has no [nominal]") from None
    return LoadedModel(loaded.source, model, model.target_offset, None, False)


def _seed(targets: Targets, seed_deg: str | None, dof: int) -> Array:
    if targets.q is not None:
        if seed_deg is not None:
            raise InputError("--seed-deg: the targets file has joint columns, which seed each row")
        return targets.q
    if seed_deg is None:
        return np.zeros((len(targets.names), dof))
    try:
        values = [float(v) for v in seed_deg.split(",")]
    except ValueError:
        raise InputError(f"--seed-deg {seed_deg!r}: give {dof} numbers, comma-separated") from None
    if len(values) != dof or not all(math.isfinite(v) for v in values):
        raise InputError(f"--seed-deg {seed_deg!r}: give {dof} finite numbers, comma-separated")
    return np.broadcast_to(np.radians(values), (len(targets.names), dof))


def _refuse(targets: Targets, comp: Compensation) -> None:
    """Targets the solver did not reach: exit 2 (a user error: the point is out of
    reach); answers that cannot be right (outside the limits, inside the base, far from
    the nominal solution): exit 3 with the likely cause. Nothing is written either way."""

    def named(rows: list[int]) -> str:
        shown = "; ".join(f"{targets.names[k]}: {comp.why_not[k]}" for k in rows[:NAMED])
        return shown + (f" (and {len(rows) - NAMED} more)" if len(rows) > NAMED else "")

    n = len(comp.kind)
    unreached = [k for k in range(n) if comp.kind[k] == UNREACHED]
    if unreached:
        raise InputError(
            f"{len(unreached)} of {n} targets cannot be reached with the calibrated model: "
            f"{named(unreached)}; nothing written"
        )
    refused = [k for k in range(n) if comp.kind[k] != REACHED]
    if refused:
        raise AcceptanceError(
            CHECK,
            f"{len(refused)} of {n} targets have no acceptable joints: {named(refused)}; "
            f"nothing written; likely cause: {CAUSE[comp.kind[refused[0]]]}",
        )


def _csv(targets: Targets, comp: Compensation) -> str:
    dof = comp.q.shape[1]
    head = ["name", *(f"q{i}" for i in range(1, dof + 1)), "x", "y", "z"]
    head += [f"flange_{c}" for c in ("x", "y", "z", "rx", "ry", "rz")] + ["correction_mm"]
    lines = [",".join(head)]
    for k, name in enumerate(targets.names):
        T = comp.T_base_flange_nominal[k]
        values = [
            *np.degrees(comp.q[k]),
            *targets.xyz[k],
            *T[:3, 3],
            *np.degrees(so3_log(T[:3, :3])),
            comp.correction_mm[k],
        ]
        lines.append(",".join([name, *(f"{round(float(v), 9) + 0.0:.9f}" for v in values)]))
    return "\n".join(lines) + "\n"


@click.command("compensate")
@click.option("--model", "model_spec", required=True, help="Calibrated model (calibrate --out).")
@click.option(
    "--targets",
    "targets_path",
    required=True,
    help="CSV name,x,y,z (mm); optional ori_w,ori_x,ori_y,ori_z (flange orientation) and "
    "q1..qn (deg: the joints the program uses today, which pick the configuration), "
    "payload_kg (the payload each point is reached with, for a compliance term).",
)
@click.option("--out", "out_path", required=True, help="Write the joint targets CSV here.")
@click.option(
    "--frame",
    type=click.Choice(["base", "sensor"]),
    default="base",
    show_default=True,
    help="The targets' frame: the robot base, or the sensor the model was calibrated with.",
)
@click.option("--target", "target_name", help="Which target of a several-target model.")
@click.option(
    "--seed-deg",
    help="Joints (deg, comma-separated) to start from when the targets have no q columns "
    "(default: all 0).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def compensate_command(
    model_spec: str,
    targets_path: str,
    out_path: str,
    frame: str,
    target_name: str | None,
    seed_deg: str | None,
    as_json: bool,
) -> None:
    """Joint targets that bring the real robot's target to intended points.

    Writes name,q1..qn,x,y,z (the joints to command, deg, and the intended point as
    given), then the nominal model's flange pose at those joints (flange_x..z mm,
    flange_rx..rz: rotation vector, deg) for a controller that takes Cartesian targets,
    and correction_mm: how far the nominal model would have been from the point.
    """
    check_output_file(out_path)
    loaded = load_model(model_spec)
    if not loaded.calibrated or loaded.T_sensor_base is None:
        raise InputError(
            f"--model {model_spec}: a nominal model; compensate needs a calibrated model "
            "(cellcal calibrate --out, or model.toml of a campaign's report)"
        )
    require_limits(loaded.model, f"--model {model_spec}")
    target_offset = loaded.target_offset
    if target_name is not None:
        if not loaded.targets or target_name not in loaded.targets:
            names = ", ".join(loaded.targets or {}) or "none named"
            raise InputError(f"--target {target_name}: not in the model ({names})")
        target_offset = loaded.targets[target_name]
    dof = loaded.model.dof
    targets = read_targets(targets_path, dof)
    p, R = targets.xyz, targets.orientations
    if frame == "sensor":
        T_base_sensor = invert(loaded.T_sensor_base)
        p = apply(T_base_sensor, p)
        if R is not None:
            R = T_base_sensor[:3, :3] @ R
    nominal = _nominal(loaded).model
    seed = _seed(targets, seed_deg, dof)
    if R is None and targets.q is not None:
        # Keep the orientation the program has today at its joints (nominal model).
        R = flange_transforms(nominal, seed)[:, :3, :3]
    comp = compensate(loaded.model, target_offset, nominal, p, R, seed, targets.conditions)
    _refuse(targets, comp)
    write_atomically(out_path, _csv(targets, comp))
    summary = {
        "out": out_path,
        # the model used, by the name a cell's database knows it by (cellcal models --cell)
        "model": str(Path(model_spec).resolve()) if Path(model_spec).is_file() else model_spec,
        "model_digest": model_digest(read_text(model_spec, "a calibrated model")),
        "n_targets": len(p),
        "frame": frame,
        "orientation": "given"
        if targets.orientations is not None
        else ("kept from the q columns" if targets.q is not None else "free (position only)"),
        "rms_correction_mm": float(np.sqrt(np.mean(comp.correction_mm**2))),
        "max_correction_mm": float(comp.correction_mm.max()),
        "max_residual_mm": float(comp.residual_mm.max()),
    }
    if as_json:
        print_json(summary)
        return
    click.echo(
        f"{len(p)} compensated targets in {out_path}: correction RMS "
        f"{summary['rms_correction_mm']:.4f} mm, max {summary['max_correction_mm']:.4f} mm "
        f"(orientation {summary['orientation']})"
    )
    click.echo(f"model: {summary['model']}, digest {summary['model_digest']}")
