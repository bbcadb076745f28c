"""``cellcal plan``: a campaign's plan without moving anything."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

import click
import numpy as np

from cellcal.commands.output import print_json
from cellcal.commands.run import cell_config
from cellcal.config import CellConfig
from cellcal.daemon.plan import (
    CALIBRATION,
    Plan,
    cell_seconds,
    expected_rms,
    make_plan,
    plan_identifiability,
    workspace_poses,
)
from cellcal.errors import InputError
from cellcal.modelfiles import load_model, write_atomically

WHY = {"rank": "not identifiable from these poses", "weak": "hidden by noise", "fixed": "fixed"}


def plan_csv(plan: Plan, dof: int) -> str:
    """``idx,role,region,reachable,q1..qN,x,y,z`` (joints deg; target mm, base frame) and
    an added ``reason`` column: every pose, then the unreachable ones (no idx, empty
    joints, ``reachable`` = ``no`` and the reason)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    joints = [f"q{i}" for i in range(1, dof + 1)]
    w.writerow(["idx", "role", "region", "reachable", *joints, "x", "y", "z", "reason"])
    for p in plan.poses:
        values = [*np.degrees(p.q), *p.target_mm]
        w.writerow([p.idx, p.role, p.region, "yes", *(f"{v:.6f}" for v in values), ""])
    for u in plan.unreachable:
        xyz = [f"{v:.6f}" for v in u.target_mm]
        w.writerow(["", u.role, u.region, "no", *([""] * dof), *xyz, u.reason])
    return buf.getvalue()


def _poses(plan: Plan) -> list[dict[str, Any]]:
    """The plan's poses for ``--json`` (joints deg, target mm), unreachable ones last."""
    out: list[dict[str, Any]] = [
        {
            "idx": p.idx,
            "role": p.role,
            "region": p.region,
            "reachable": True,
            "q_deg": [round(float(v), 6) for v in np.degrees(p.q)],
            "target_mm": [round(float(v), 6) for v in p.target_mm],
        }
        for p in plan.poses
    ]
    out += [
        {
            "idx": None,
            "role": u.role,
            "region": u.region,
            "reachable": False,
            "reason": u.reason,
            "target_mm": [round(float(v), 6) for v in u.target_mm],
        }
        for u in plan.unreachable
    ]
    return out


@click.command("plan")
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option("--mock", is_flag=True, help="The bundled simulated cell (without --config).")
@click.option(
    "--optimal",
    type=click.IntRange(0, 10000),
    help="Pick this many calibration poses that identify the model best (D-optimal); "
    "overrides campaign.optimal_poses.",
)
@click.option(
    "--criterion",
    type=click.Choice(["D", "I"]),
    help="What --optimal optimises: D, the parameters' confidence volume; I, the mean "
    "prediction variance in the cube and the validation regions; overrides "
    "campaign.optimal_criterion (D unless set).",
)
@click.option("--out", "out_path", help="Write the plan as CSV here.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def plan(
    config_path: str | None,
    mock: bool,
    optimal: int | None,
    criterion: str | None,
    out_path: str | None,
    as_json: bool,
) -> None:
    """Every pose of the campaign's plan, reachable or not and why, the condition number
    of the calibration poses and the parameters they identify, and the cell time it
    takes, and the error a calibration from these poses is expected to leave in the
    cube and the validation regions (in units of the sensor's noise); nothing connects
    or moves. The robot's start is the configuration's robot.home_deg (the campaign
    starts there too), never the robot's reading. --optimal 0: the whole cube."""
    config, source = cell_config(config_path, mock)
    campaign = config.campaign
    if optimal is not None:
        campaign = campaign.model_copy(update={"optimal_poses": optimal})
    if criterion is not None:
        campaign = campaign.model_copy(update={"optimal_criterion": criterion})
    nominal = load_model(config.robot.model).model
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    if len(home) != nominal.dof:
        raise InputError(f"robot.home_deg has {len(home)} joints, the model {nominal.dof}")
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    planned = make_plan(campaign, nominal, home, offset)
    speed = _joint_speed_deg_s(config)
    summary: dict[str, Any] = {
        "config": source,
        "model": nominal.name,
        "n_poses": len(planned.poses),
        "n_calibration": planned.count(CALIBRATION),
        "n_validation": len(planned.poses) - planned.count(CALIBRATION),
        "n_unreachable": len(planned.unreachable),
        "regions": _regions(planned),
    }
    ident = plan_identifiability(nominal, planned, offset)
    if ident is not None:
        summary["condition_number"] = ident.condition_number
        summary["identified"] = list(ident.identified_names)
        summary["unidentifiable"] = {
            ident.specs[i].name: WHY[ident.reason(i)] for i in ident.unidentifiable
        }
    q_cal = np.array([p.q for p in planned.poses if p.role == CALIBRATION])
    workspace = workspace_poses(campaign, nominal, home, offset)
    expected = expected_rms(nominal, q_cal, offset, workspace)
    if expected is not None:
        summary["expected_rms_sigma"] = expected
    if planned.selection is not None:
        sel = planned.selection
        summary["optimal"] = {
            "criterion": sel.criterion,
            "n": len(sel.chosen),
            "candidates": planned.candidates,
            "log_det": sel.log_det,
            "exchanges": sel.exchanges,
            "history": list(sel.history),
        }
    summary["dwell_s"] = campaign.dwell_s
    summary["joint_speed_deg_s"] = speed
    q_all = np.array([p.q for p in planned.poses]).reshape(-1, nominal.dof)
    seconds = cell_seconds(q_all, home, math.radians(speed), campaign.dwell_s)
    summary["cell_time_min"] = seconds / 60.0
    if out_path is not None:
        write_atomically(out_path, plan_csv(planned, nominal.dof))
        summary["out"] = out_path
    if as_json:
        print_json({**summary, "poses": _poses(planned)})
        return
    _echo(planned, summary)


def _regions(p: Plan) -> dict[str, int]:
    out: dict[str, int] = {}
    for pose in p.poses:
        key = f"{pose.role} {pose.region}"
        out[key] = out.get(key, 0) + 1
    return out


def _joint_speed_deg_s(config: CellConfig) -> float:
    """The joint speed the cell time assumes: simulation.joint_speed_deg_s (60 °/s unless
    set; the simulated robot's full speed) × robot.speed. A real controller's differs."""
    return float(config.simulation.joint_speed_deg_s * config.robot.speed)


def _echo(p: Plan, s: dict[str, Any]) -> None:
    click.echo(f"  {'idx':>4} {'role':<12}{'region':<7} {'q1..qN (deg)':<48} target (mm)")
    for pose in p.poses:
        q = " ".join(f"{v:7.2f}" for v in np.degrees(pose.q))
        t = " ".join(f"{v:8.1f}" for v in pose.target_mm)
        click.echo(f"  {pose.idx:>4} {pose.role:<12}{pose.region:<7} {q:<48} {t}")
    for u in p.unreachable:
        t = " ".join(f"{v:8.1f}" for v in u.target_mm)
        click.echo(f"  {'—':>4} {u.role:<12}{u.region:<7} unreachable: {u.reason} at {t}")
    click.echo(
        f"{s['n_poses']} poses ({s['n_calibration']} calibration, {s['n_validation']} "
        f"validation), {s['n_unreachable']} unreachable; "
        + ", ".join(f"{k}: {n}" for k, n in s["regions"].items())
    )
    if "optimal" in s:
        o = s["optimal"]
        click.echo(
            f"{o['criterion']}-optimal: {o['n']} calibration poses of {o['candidates']} "
            f"reachable candidates (log det {o['log_det']:.2f}, {o['exchanges']} exchanges)"
        )
    if "condition_number" in s:
        click.echo(
            f"condition number {s['condition_number']:.4g}; identifies "
            f"{len(s['identified'])} parameters: {', '.join(s['identified'])}"
        )
        left = "; ".join(f"{k} ({why})" for k, why in s["unidentifiable"].items())
        click.echo(f"left at nominal: {left or 'none'}")
    if "expected_rms_sigma" in s:
        click.echo(
            f"expected RMS error in the cube and the validation regions after calibration: "
            f"{s['expected_rms_sigma']:.3f} × the sensor's noise (σ per coordinate)"
        )
    click.echo(
        f"cell time about {s['cell_time_min']:.1f} min: {s['dwell_s']:g} s dwell per pose, "
        f"moves at {s['joint_speed_deg_s']:g} °/s on the joint that turns most "
        "(simulation.joint_speed_deg_s × robot.speed; a real controller's profile differs)"
    )
