"""``cellcal plan``: a campaign's plan without moving anything."""

from __future__ import annotations

import csv
import io
import math
from importlib import resources
from typing import TYPE_CHECKING, Any

import click
import numpy as np

from cellcal.commands.output import print_json
from cellcal.errors import InputError, UserError
from cellcal.files.outputs import check_output_file
from cellcal.files.text import read_toml

if TYPE_CHECKING:  # imported when the command runs, after its first progress line
    from cellcal.calib.geometry import Array
    from cellcal.calib.identifiability import Identifiability
    from cellcal.calib.robot_model import RobotModel
    from cellcal.campaign.plan import Plan
    from cellcal.config import CampaignConfig, CellConfig

#: The bundled simulated cell (``--mock`` without ``--config``), as ``cellcal run`` has it.
BUNDLED = "mock-cell.toml"

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


def _glance(config_path: str | None, mock: bool) -> dict[str, Any]:
    """The configuration's [campaign] table as written, unchecked, or {} if it cannot be
    read: enough to say early what the plan will do. Loading the configuration itself
    imports most of the numerics (its device families, the robot models), which takes
    about a second on a busy machine; the checked configuration follows."""
    try:
        if config_path is not None:
            data = read_toml(config_path)
        elif mock:
            with resources.as_file(resources.files("cellcal") / "data" / BUNDLED) as p:
                data = read_toml(p)
        else:
            return {}
    except (UserError, OSError):
        return {}
    campaign = data.get("campaign")
    return campaign if isinstance(campaign, dict) else {}


def _progress(line: str) -> None:
    click.echo(f"planning: {line}", err=True)


def _silent(line: str) -> None:
    """A quick plan (the cube alone) says nothing while it works."""


def _opening(optimal: object, criterion: object, region: object) -> str | None:
    """The first progress line of a plan that takes more than a moment (poses to choose,
    or workspace points to draw), None for one that does not."""
    box = region == "workspace"
    if isinstance(optimal, int) and not isinstance(optimal, bool) and optimal > 0:
        where = "drawn over the workspace box" if box else "of the cube"
        return f"{optimal} {criterion}-optimal calibration poses from candidates {where} …"
    if box:
        return "the expected error is judged at poses drawn over the workspace box …"
    return None


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
    "prediction variance in the region (--region); overrides campaign.optimal_criterion "
    "(D unless set).",
)
@click.option(
    "--region",
    type=click.Choice(["cube", "workspace"]),
    help="Where the robot will work: the cube and the validation regions, or the workspace "
    "box; --optimal chooses from candidates there and the expected error is judged there; "
    "overrides campaign.region (cube unless set).",
)
@click.option("--out", "out_path", help="Write the plan as CSV here.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def plan(
    config_path: str | None,
    mock: bool,
    optimal: int | None,
    criterion: str | None,
    region: str | None,
    out_path: str | None,
    as_json: bool,
) -> None:
    """Every pose of the campaign's plan, reachable or not and why, the condition number
    of the calibration poses and the parameters they identify, and the cell time it
    takes, and the error a calibration from these poses is expected to leave in the
    cube and the validation regions (in units of the sensor's noise); nothing connects
    or moves. The robot's start is the configuration's robot.home_deg (the campaign
    starts there too), never the robot's reading. --optimal 0: the whole cube.
    --region workspace: the expected error over the workspace box, and --optimal's
    candidates drawn there. A plan that chooses poses or draws them says what it is
    doing on stderr, lines starting "planning: "."""
    if out_path is not None:
        check_output_file(out_path)  # before the work: a device or FIFO is refused
    written = _glance(config_path, mock)
    early = _opening(
        optimal if optimal is not None else written.get("optimal_poses", 0),
        criterion or written.get("optimal_criterion", "D"),
        region or written.get("region", "cube"),
    )
    if early is not None:  # before anything slow: the numerics load after this line
        _progress(early)
    from cellcal.commands.run import cell_config

    config, source = cell_config(config_path, mock)
    campaign = config.campaign
    if optimal is not None:
        campaign = campaign.model_copy(update={"optimal_poses": optimal})
    if criterion is not None:
        campaign = campaign.model_copy(update={"optimal_criterion": criterion})
    if region is not None:
        campaign = campaign.model_copy(update={"region": region})
    opening = _opening(campaign.optimal_poses, campaign.optimal_criterion, campaign.region)
    if opening is not None and opening != early:
        _progress(opening)
    from cellcal.campaign.plan import (
        CALIBRATION,
        cell_seconds,
        expected_rms,
        make_plan,
        plan_identifiability,
        workspace_poses,
    )
    from cellcal.campaign.plan_checks import check_inputs
    from cellcal.campaign.plan_region import region_text
    from cellcal.files.models import load_model, write_atomically

    say = _progress if opening is not None else _silent
    nominal = load_model(config.robot.model).model
    home = np.radians(np.asarray(config.robot.home_deg, dtype=np.float64))
    if len(home) != nominal.dof:
        raise InputError(f"robot.home_deg has {len(home)} joints, the model {nominal.dof}")
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=np.float64)
    check_inputs(campaign, nominal, home, f"robot.model {config.robot.model}")
    workspace = workspace_poses(campaign, nominal, home, offset, progress=say)
    planned = make_plan(campaign, nominal, home, offset, workspace=workspace, progress=say)
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
        summary.update(_identified(ident))
    q_cal = np.array([p.q for p in planned.poses if p.role == CALIBRATION])
    summary["region"] = campaign.region
    summary["expected_region"] = region_text(campaign)
    summary["expected_points"] = len(workspace)
    expected = expected_rms(nominal, q_cal, offset, workspace)
    if expected is not None:
        summary["expected_rms_sigma"] = expected
    if planned.selection is not None:
        sel = planned.selection
        summary["optimal"] = {
            "criterion": sel.criterion,
            "n": len(sel.chosen),
            "candidates": planned.candidates,
            "candidates_drawn": planned.drawn,
            "candidates_unreachable": planned.drawn - planned.candidates,
            "log_det": sel.log_det,
            "exchanges": sel.exchanges,
            "history": list(sel.history),
        }
    summary["dwell_s"] = campaign.dwell_s
    summary["joint_speed_deg_s"] = speed
    q_all = np.array([p.q for p in planned.poses]).reshape(-1, nominal.dof)
    seconds = cell_seconds(q_all, home, math.radians(speed), campaign.dwell_s)
    summary["cell_time_min"] = seconds / 60.0
    summary["moves_leaving_box"] = _leaving(campaign, nominal, home, offset, q_all)
    if out_path is not None:
        write_atomically(out_path, plan_csv(planned, nominal.dof))
        summary["out"] = out_path
    if as_json:
        print_json({**summary, "poses": _poses(planned)})
        return
    _echo(planned, summary)


def _leaving(
    campaign: CampaignConfig, model: RobotModel, home: Array, offset: Array, q: Array
) -> list[dict[str, Any]]:
    """The moves that leave the workspace box on the way (the safety gate refuses them):
    the pose moved to, how far (mm), which point (flange or target), where on the way
    (fraction of the move) and where (mm, base frame)."""
    from cellcal.campaign.plan_checks import moves_outside
    from cellcal.campaign.plan_region import box

    lo, hi = box(campaign)
    return [
        {
            "idx": k,
            "excess_mm": round(e.excess_mm, 3),
            "point": e.point,
            "fraction": round(e.fraction, 4),
            "at_mm": [round(float(v), 3) for v in e.where_mm],
        }
        for k, e in moves_outside(model, home, q, offset, lo, hi).items()
    ]


def _identified(ident: Identifiability) -> dict[str, Any]:
    """What the calibration poses identify, as the calibration counts it: the robot's
    kinematic parameters and the target offset (``identified``), the sensor frame's apart
    (``identified_frame``); the condition number of them all, every coordinate weighted
    alike (the calibration weighs each by 1/σ of its measurement, which moves it)."""
    frame = [i for i in ident.identified if ident.specs[i].kind.startswith("frame")]
    return {
        "condition_number": ident.condition_number,
        "condition_number_equal_weights": ident.condition_number,
        "identified": [ident.specs[i].name for i in ident.identified if i not in frame],
        "identified_frame": [ident.specs[i].name for i in frame],
        "unidentifiable": {ident.specs[i].name: WHY[ident.reason(i)] for i in ident.unidentifiable},
    }


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
    regions = [x.region for x in p.poses] + [u.region for u in p.unreachable]
    w = max([7, *(len(r) + 1 for r in regions)])
    click.echo(f"  {'idx':>4} {'role':<12}{'region':<{w}} {'q1..qN (deg)':<48} target (mm)")
    for pose in p.poses:
        q = " ".join(f"{v:7.2f}" for v in np.degrees(pose.q))
        t = " ".join(f"{v:8.1f}" for v in pose.target_mm)
        click.echo(f"  {pose.idx:>4} {pose.role:<12}{pose.region:<{w}} {q:<48} {t}")
    for u in p.unreachable:
        t = " ".join(f"{v:8.1f}" for v in u.target_mm)
        click.echo(f"  {'—':>4} {u.role:<12}{u.region:<{w}} unreachable: {u.reason} at {t}")
    click.echo(
        f"{s['n_poses']} poses ({s['n_calibration']} calibration, {s['n_validation']} "
        f"validation), {s['n_unreachable']} unreachable; "
        + ", ".join(f"{k}: {n}" for k, n in s["regions"].items())
    )
    if "optimal" in s:
        o = s["optimal"]
        where = "drawn over the workspace box" if s["region"] == "workspace" else "in the cube"
        click.echo(
            f"{o['criterion']}-optimal: {o['n']} calibration poses of {o['candidates']} "
            f"reachable candidates {where} ({o['candidates_unreachable']} of "
            f"{o['candidates_drawn']} unreachable; log det {o['log_det']:.2f}, "
            f"{o['exchanges']} exchanges)"
        )
    if "condition_number" in s:
        click.echo(
            f"condition number {s['condition_number']:.4g} with equal weights (the "
            "calibration weighs each coordinate by its measured σ, which moves it)"
        )
        frame = s["identified_frame"]
        click.echo(
            f"identifies {len(s['identified'])} parameters of the robot and target offset"
            f" (+ {len(frame)} of the sensor frame): {', '.join(s['identified'])}"
            + (f"; sensor frame: {', '.join(frame)}" if frame else "")
        )
        left = "; ".join(f"{k} ({why})" for k, why in s["unidentifiable"].items())
        click.echo(f"left at nominal: {left or 'none'}")
    if "expected_rms_sigma" in s:
        click.echo(
            f"expected RMS error {s['expected_region']} after calibration: "
            f"{s['expected_rms_sigma']:.3f} × the sensor's noise (σ per coordinate), "
            f"judged at {s['expected_points']} reachable poses"
        )
    leaving = s["moves_leaving_box"]
    if leaving:
        worst = max(leaving, key=lambda m: m["excess_mm"])
        shown = ", ".join(f"{m['idx']} ({m['excess_mm']:.1f} mm)" for m in leaving[:10])
        more = f" and {len(leaving) - 10} more" if len(leaving) > 10 else ""
        click.echo(
            f"{len(leaving)} moves leave the workspace box on the way, which the safety "
            f"gate refuses (the joint move to pose, by how much): {shown}{more}; the worst "
            f"by {worst['excess_mm']:.1f} mm (its {worst['point']}): widen "
            "campaign.workspace_min_mm/max_mm or move the cube"
        )
    click.echo(
        f"cell time about {s['cell_time_min']:.1f} min: {s['dwell_s']:g} s dwell per pose, "
        f"moves at {s['joint_speed_deg_s']:g} °/s on the joint that turns most "
        "(simulation.joint_speed_deg_s × robot.speed; a real controller's profile differs)"
    )
