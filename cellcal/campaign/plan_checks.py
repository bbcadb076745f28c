"""What a plan must not start with, checked before any work (pure): a robot model
without finite, plausible joint limits, a home outside them, and a plan whose work is
out of proportion (too many grid points, validation regions or poses to solve, an
optimal selection too large). Each is refused with one line naming the bound. And what
a campaign must not start with once its plan is made: a move between its poses that
leaves the workspace box on the way (:func:`refuse_moves_outside`), which the safety
gate would refuse in the middle of the campaign."""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.pose_selection import SELECTION_BUDGET
from cellcal.calib.robot_model import RobotModel, require_limits
from cellcal.campaign.plan_region import REGION_CANDIDATES, REGION_MAX_DRAWS, WORKSPACE, box
from cellcal.config import CampaignConfig
from cellcal.drivers.safety import PathExcursion, path_excursion
from cellcal.errors import CampaignError, InputError

#: The campaign event that records the joint limits a campaign was started with.
LIMITS_EVENT = "limits"
_LIMITS_SAID = "joint limits (deg, min and max per joint) the plan was made within: "
#: Wrist orientations tried at each grid point when ``campaign.optimal_poses`` is set.
CANDIDATE_ORIENTATIONS = 4
#: Bounds on the work a plan causes, checked before it starts (:func:`check_size`): the
#: cube's grid points (each a pose to solve and visit; with campaign.optimal_poses each
#: is tried at CANDIDATE_ORIENTATIONS orientations), the validation regions, and every
#: pose the plan solves by inverse kinematics.
MAX_GRID_POINTS = 2000
MAX_VALIDATION_REGIONS = 50
MAX_PLAN_POSES = 20000


def check_inputs(
    cfg: CampaignConfig, model: RobotModel, home_q: Array, source: str | None = None
) -> None:
    """Refuse, one line each, what a plan must not start with: a robot model without
    finite, plausible joint limits (``source`` names it, else its name), a home outside
    them, or a plan too large to compute (:func:`check_size`)."""
    require_limits(model, source or f"robot model {model.name!r}")
    home = np.asarray(home_q, dtype=np.float64)
    lo, hi = model.limits
    if home.shape == (model.dof,):
        j = model.joint_outside_limits(home)
        if j is not None:
            raise InputError(
                f"robot.home_deg: joint {j + 1} at {np.degrees(home[j]):.6g}° is outside its "
                f"limits {np.degrees(lo[j]):.6g}..{np.degrees(hi[j]):.6g}°"
            )
    check_size(cfg)


def check_size(cfg: CampaignConfig) -> None:
    """Refuse, in one line naming the bound, a plan whose work is out of proportion:
    more than :data:`MAX_GRID_POINTS` grid points, :data:`MAX_VALIDATION_REGIONS`
    validation regions or :data:`MAX_PLAN_POSES` poses to solve, or an optimal selection
    of more than ``SELECTION_BUDGET`` chosen × candidates (its time grows so)."""
    nx, ny, nz = cfg.grid
    grid = nx * ny * nz
    if grid > MAX_GRID_POINTS:
        raise InputError(
            f"campaign.grid {nx}×{ny}×{nz} is {grid} points: at most {MAX_GRID_POINTS} (each "
            "is a pose to solve and visit); for fewer, better poses choose "
            "campaign.optimal_poses from a coarser grid"
        )
    regions = len(cfg.validation_regions_mm)
    if regions > MAX_VALIDATION_REGIONS:
        raise InputError(
            f"campaign.validation_regions_mm has {regions} regions: at most "
            f"{MAX_VALIDATION_REGIONS}"
        )
    if cfg.optimal_poses and cfg.region == WORKSPACE:
        candidates, solved = REGION_CANDIDATES, REGION_MAX_DRAWS
    else:
        candidates = grid * (CANDIDATE_ORIENTATIONS if cfg.optimal_poses else 1)
        solved = candidates
    solved += cfg.validation_inside + regions * cfg.validation_per_region
    if solved > MAX_PLAN_POSES:
        raise InputError(
            f"the plan has {solved} poses to solve (campaign.grid, validation_inside, "
            f"validation_per_region × {regions} regions): at most {MAX_PLAN_POSES}"
        )
    n = cfg.optimal_poses
    if n and min(n, candidates) * candidates > SELECTION_BUDGET:
        most = SELECTION_BUDGET // candidates
        raise InputError(
            f"campaign.optimal_poses (--optimal) {n} of {candidates} candidates: at most "
            f"{most} from that many (the selection's work grows as chosen × candidates, "
            f"bounded at {SELECTION_BUDGET:,}); choose fewer or a coarser campaign.grid"
        )


def moves_outside(
    model: RobotModel,
    home_q: Array,
    q: Array,
    target_offset: Array,
    box_min_mm: Array,
    box_max_mm: Array,
) -> dict[int, PathExcursion]:
    """The poses (index into ``q``, N×n rad, visited in order from ``home_q``) whose
    joint move from the pose before leaves the workspace box on the way or at its end —
    flange or target, sampled as the safety gate samples it, which refuses such a move —
    each with its worst point."""
    out: dict[int, PathExcursion] = {}
    here = np.asarray(home_q, dtype=np.float64)
    for k, row in enumerate(np.asarray(q, dtype=np.float64)):
        far = path_excursion(model, here, row, target_offset, box_min_mm, box_max_mm)
        if far is not None:
            out[k] = far
        here = row
    return out


def refuse_moves_outside(
    cfg: CampaignConfig,
    model: RobotModel,
    home_q: Array,
    poses: Sequence[tuple[int, Array]],
    target_offset: Array,
) -> None:
    """Refuse, in one line, a campaign whose plan moves out of the workspace box on the
    way from one pose to the next (``poses``: each pose's number, as the engine numbers
    them, and its joints, rad, in the order visited from ``home_q``), as the safety gate
    samples the move: the first such move, from which pose to which and by how far,
    how many there are and the worst."""
    if not poses:
        return
    lo, hi = box(cfg)
    q = np.array([p[1] for p in poses], dtype=np.float64).reshape(len(poses), -1)
    out = moves_outside(model, home_q, q, target_offset, lo, hi)
    if not out:
        return
    k, first = next(iter(out.items()))
    start = "home (robot.home_deg)" if k == 0 else f"pose {poses[k - 1][0]}"
    if first.fraction == 0.0:
        when = "at its start"
    elif first.fraction == 1.0:
        when = "at its end"
    else:
        when = f"on the way, {100 * first.fraction:.0f} % into the joint move"
    at = np.round(first.where_mm, 1).tolist()
    worst = max(out.values(), key=lambda e: e.excess_mm)
    more = (
        f"; {len(out)} of its {len(poses)} moves leave it, the worst by "
        f"{worst.excess_mm:.1f} mm (cellcal plan lists them)"
        if len(out) > 1
        else ""
    )
    raise CampaignError(
        f"the plan's joint move from {start} to pose {poses[k][0]} leaves the workspace "
        f"box by {first.excess_mm:.1f} mm {when} (its {first.point} at {at} mm), which "
        f"the safety gate refuses{more}: widen campaign.workspace_min_mm/max_mm or move "
        "the cube; nothing was moved"
    )


def limits_record(limits_deg: tuple[tuple[float, float], ...]) -> str:
    """The message of the :data:`LIMITS_EVENT` a campaign is created with."""
    return _LIMITS_SAID + json.dumps([list(pair) for pair in limits_deg])


def same_limits(
    campaign_id: int,
    recorded: list[str],
    limits_deg: tuple[tuple[float, float], ...],
    model_spec: str,
) -> None:
    """A resumed campaign moves within the limits it was started with (``recorded``: the
    messages of its :data:`LIMITS_EVENT`): refuse, naming the joint, a robot model whose
    limits changed since. A campaign of a version that did not record them has only the
    model's own, which the plan checked."""
    if not recorded or not recorded[0].startswith(_LIMITS_SAID):
        return
    try:
        then = [(float(a), float(b)) for a, b in json.loads(recorded[0][len(_LIMITS_SAID) :])]
    except (ValueError, TypeError):
        raise CampaignError(
            f"campaign {campaign_id}: its recorded joint limits are unreadable"
        ) from None
    if len(then) != len(limits_deg):
        raise CampaignError(
            f"campaign {campaign_id} was started with a {len(then)}-joint robot model; "
            f"robot.model {model_spec} has {len(limits_deg)}; start a new campaign"
        )
    for i, ((a, b), (c, d)) in enumerate(zip(then, limits_deg, strict=True), start=1):
        if abs(a - c) > 1e-6 or abs(b - d) > 1e-6:
            raise CampaignError(
                f"campaign {campaign_id} was started with joint {i}'s limits {a:g}..{b:g}°; "
                f"robot.model {model_spec} now gives {c:g}..{d:g}°: a resumed campaign "
                "keeps the limits it was started with; restore them or start a new campaign"
            )
