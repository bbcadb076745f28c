"""``cellcal plan``: a campaign's plan without moving anything."""

from __future__ import annotations

import math
from typing import Any

import click
import numpy as np

from cellcal.calib.error_model import State, jacobian, parameter_specs
from cellcal.calib.identifiability import analyse as analyse_identifiability
from cellcal.commands.output import print_json
from cellcal.commands.run import cell_config
from cellcal.daemon.plan import CALIBRATION, Plan, make_plan
from cellcal.modelfiles import load_model, write_atomically

WHY = {"rank": "not identifiable from these poses", "weak": "hidden by noise", "fixed": "fixed"}


def plan_csv(plan: Plan, dof: int) -> str:
    """``idx,role,region,reachable,q1..qN,x,y,z`` (joints deg; target mm, base frame):
    every pose, then the unreachable ones with empty joints and the reason."""
    head = ["idx", "role", "region", "reachable", *(f"q{i}" for i in range(1, dof + 1))]
    lines = [",".join([*head, "x", "y", "z", "reason"])]
    for p in plan.poses:
        values = [*np.degrees(p.q), *p.target_mm]
        row = [str(p.idx), p.role, p.region, "yes", *(f"{v:.6f}" for v in values), ""]
        lines.append(",".join(row))
    for u in plan.unreachable:
        row = ["", u.role, u.region, "no", *([""] * dof), *(f"{v:.6f}" for v in u.target_mm)]
        lines.append(",".join([*row, f'"{u.reason}"']))
    return "\n".join(lines) + "\n"


@click.command("plan")
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option("--mock", is_flag=True, help="The bundled simulated cell (without --config).")
@click.option(
    "--optimal",
    type=click.IntRange(0, 10000),
    help="Pick this many calibration poses that identify the model best (D-optimal); "
    "overrides campaign.optimal_poses.",
)
@click.option("--out", "out_path", help="Write the plan as CSV here.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def plan(
    config_path: str | None, mock: bool, optimal: int | None, out_path: str | None, as_json: bool
) -> None:
    """Every pose of the campaign's plan, reachable or not and why, the condition number
    of the calibration poses and the parameters they identify, and the cell time it
    takes; nothing connects or moves. The robot's home joints come from the
    configuration (robot.home_deg)."""
    config, source = cell_config(config_path, mock)
    campaign = config.campaign
    if optimal is not None:
        campaign = campaign.model_copy(update={"optimal_poses": optimal})
    nominal = load_model(config.robot.model).model
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    planned = make_plan(campaign, nominal, home, offset)
    q_cal = np.array([p.q for p in planned.poses if p.role == CALIBRATION])
    summary: dict[str, Any] = {
        "config": source,
        "model": nominal.name,
        "n_poses": len(planned.poses),
        "n_calibration": planned.count(CALIBRATION),
        "n_validation": len(planned.poses) - planned.count(CALIBRATION),
        "n_unreachable": len(planned.unreachable),
        "regions": _regions(planned),
    }
    if len(q_cal):
        state = State(nominal, offset, np.eye(3), np.zeros(3), np.zeros(3))
        specs = parameter_specs(nominal)
        _, J = jacobian(state, q_cal, specs)
        ident = analyse_identifiability(J.reshape(-1, len(specs)), specs)
        summary["condition_number"] = ident.condition_number
        summary["identified"] = [specs[i].name for i in ident.identified]
        summary["unidentifiable"] = {
            specs[i].name: WHY[ident.reason(i)] for i in ident.unidentifiable
        }
    if planned.selection is not None:
        summary["optimal"] = {
            "n": len(planned.selection.chosen),
            "candidates": planned.candidates,
            "log_det": planned.selection.log_det,
            "exchanges": planned.selection.exchanges,
        }
    summary["cell_time_min"] = _minutes(planned, home, config, campaign.dwell_s)
    if out_path is not None:
        write_atomically(out_path, plan_csv(planned, nominal.dof))
        summary["out"] = out_path
    if as_json:
        print_json(summary)
        return
    _echo(planned, summary, campaign.dwell_s)


def _regions(p: Plan) -> dict[str, int]:
    out: dict[str, int] = {}
    for pose in p.poses:
        key = f"{pose.role} {pose.region}"
        out[key] = out.get(key, 0) + 1
    return out


def _minutes(p: Plan, home: np.ndarray, config: Any, dwell_s: float) -> float:
    """Dwell at every pose plus each move, its largest joint turn at
    simulation.joint_speed_deg_s × robot.speed (an estimate: a real controller's profile
    differs)."""
    speed = math.radians(config.simulation.joint_speed_deg_s) * config.robot.speed
    here, total = home, 0.0
    for pose in p.poses:
        total += float(np.abs(pose.q - here).max()) / speed + dwell_s
        here = pose.q
    return total / 60.0


def _echo(p: Plan, s: dict[str, Any], dwell_s: float) -> None:
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
            f"D-optimal: {o['n']} calibration poses of {o['candidates']} reachable candidates "
            f"(log det {o['log_det']:.2f}, {o['exchanges']} exchanges)"
        )
    if "condition_number" in s:
        click.echo(
            f"condition number {s['condition_number']:.4g}; identifies "
            f"{len(s['identified'])} parameters: {', '.join(s['identified'])}"
        )
        left = "; ".join(f"{k} ({why})" for k, why in s["unidentifiable"].items())
        click.echo(f"left at nominal: {left or 'none'}")
    click.echo(
        f"cell time about {s['cell_time_min']:.1f} min ({dwell_s:g} s dwell per pose, moves at "
        "the configured speed)"
    )
