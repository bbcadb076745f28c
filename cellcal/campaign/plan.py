"""The plan: which poses a campaign visits, computed before any motion (pure).

Calibration poses fill the paper's cube (80 points in a 200 mm cube by default) in a
serpentine order; at each point the flange is turned by a seeded rotation of up to
``orientation_variation_deg`` about each axis, which is what makes the identification
well conditioned (0 reproduces the paper's fixed orientation). Validation poses lie
inside the cube and in the paper's regions O1–O5 outside it (Table 3). Every pose is
solved by inverse kinematics of the nominal model and checked against the joint limits
and the workspace box; a pose that fails is reported as unreachable, not dropped
silently.

With ``campaign.optimal_poses`` the calibration poses are chosen from candidates: the
cube's grid points at more wrist orientations (``campaign.region = "cube"``), or poses
drawn at random over the workspace box (``"workspace"``), reachable ones only. The
region also says where the plan's expected error is judged: in the cube and the
validation regions, or at other poses drawn over the box. The validation poses are the
same whatever the region, so that reports stay comparable.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.error_model import ParameterSpec, State, jacobian, parameter_specs, predict
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import Identifiability
from cellcal.calib.identifiability import analyse as analyse_identifiability
from cellcal.calib.inverse_kinematics import solve
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.pose_selection import (
    PoseSelection,
    d_optimal,
    i_optimal,
    nearest_neighbour_order,
    prediction_rms,
)
from cellcal.calib.robot_model import RobotModel
from cellcal.campaign.plan_checks import CANDIDATE_ORIENTATIONS, check_inputs
from cellcal.campaign.plan_region import (
    CUBE,
    REGION_CANDIDATES,
    REGION_POINTS,
    WORKSPACE,
    box,
    draw_reachable,
    orientations,
)
from cellcal.config import CampaignConfig
from cellcal.errors import InputError

CALIBRATION = "calibration"
VALIDATION = "validation"
#: and their wrist turned up to this much about each axis (deg), or the campaign's own
#: orientation_variation_deg where that is more.
CANDIDATE_VARIATION_DEG = 60.0
#: The workspace points the prediction is judged at (I-optimal selection, the plan's
#: expected error): drawn like the validation poses, from another seed (so that the
#: validation poses stay held out), this many inside the cube and per validation region.
WORKSPACE_INSIDE = 60
WORKSPACE_PER_REGION = 20
WORKSPACE_SEED = 7919
#: Where a plan says what it is doing (``cellcal plan`` prints it on stderr).
Progress = Callable[[str], None]


def _quiet(message: str) -> None:
    """No progress report."""


@dataclass(frozen=True)
class PlannedPose:
    """``idx``: position in the plan; ``role``: calibration or validation; ``region``:
    ``cube``, ``workspace`` (drawn over the workspace box) or ``O1``…; ``target_mm``:
    the nominal target position (base frame); ``q``: joint readings (rad); ``payload_kg``:
    the payload it is measured with (``[campaign] payloads_kg``; None: not planned)."""

    idx: int
    role: str
    region: str
    target_mm: Array
    q: Array
    payload_kg: float | None = None


@dataclass(frozen=True)
class UnreachablePose:
    role: str
    region: str
    target_mm: Array
    reason: str


@dataclass(frozen=True)
class Plan:
    """The poses in order, the poses that cannot be reached, and with
    ``campaign.optimal_poses`` the selection: how many reachable candidates it chose
    from, how many were tried (``drawn``: the cube's grid points × orientations, or the
    poses drawn over the workspace box, reachable or not), and its criterion's figures.
    ``limits_deg``: the model's joint limits (min, max per joint, deg) the plan was made
    within, which a resumed campaign must keep (not part of the digest)."""

    poses: tuple[PlannedPose, ...]
    unreachable: tuple[UnreachablePose, ...]
    candidates: int = 0
    selection: PoseSelection | None = None
    drawn: int = 0
    limits_deg: tuple[tuple[float, float], ...] = ()

    @property
    def digest(self) -> str:
        """A fingerprint of the poses (roles and joints to 1e-9 rad): a resumed campaign
        must follow the same plan."""
        h = hashlib.sha256()
        for p in self.poses:
            h.update(f"{p.idx}:{p.role}:{p.region}:".encode())
            if p.payload_kg is not None:
                h.update(f"{p.payload_kg!r}:".encode())
            h.update(np.round(p.q, 9).tobytes())
        return h.hexdigest()[:16]

    def count(self, role: str) -> int:
        return sum(1 for p in self.poses if p.role == role)


def cube_points(cfg: CampaignConfig) -> Array:
    """Grid points of the cube in serpentine order (mm, base frame)."""
    c = np.asarray(cfg.cube_centre_mm)
    h = cfg.cube_edge_mm / 2.0
    xs, ys, zs = (np.linspace(-h, h, k) for k in cfg.grid)
    pts = []
    for i, x in enumerate(xs):
        ys_i = ys if i % 2 == 0 else ys[::-1]
        for j, y in enumerate(ys_i):
            zs_j = zs if (i * len(ys) + j) % 2 == 0 else zs[::-1]
            pts += [[x, y, z] for z in zs_j]
    return c + np.array(pts)


def _ball(rng: np.random.Generator, centre: Array, radius: float, n: int) -> Array:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = radius * rng.uniform(0, 1, n) ** (1 / 3)
    out: Array = centre + d * r[:, None]
    return out


def solve_group(
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    R0: Array,
    pts: Array,
    Rs: Array,
) -> tuple[Array, NDArray[np.bool_]]:
    """Joint readings of a group of poses and whether each was solved within the joint
    limits: from the solution at the group's centre (neighbouring poses, short moves),
    then from home for the ones that failed."""
    centre_sol = solve(model, target_offset, pts.mean(axis=0)[None], R0, home_q)
    from_centre = bool(centre_sol.ok[0])
    seed = centre_sol.q[0] if from_centre else home_q
    sol = solve(model, target_offset, pts, Rs, seed)
    retry = ~sol.ok
    if not from_centre or not retry.any():  # from home again would fail again
        return sol.q, sol.ok
    again = solve(model, target_offset, pts[retry], Rs[retry], home_q)
    q = sol.q.copy()
    q[retry] = again.q
    ok = sol.ok.copy()
    ok[retry] = again.ok
    return q, ok


def make_plan(
    cfg: CampaignConfig,
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    *,
    select: bool = True,
    workspace: Array | None = None,
    progress: Progress = _quiet,
) -> Plan:
    """The campaign's poses for ``model`` starting from ``home_q`` (rad), with the target
    at ``target_offset`` (mm, flange frame). With ``campaign.optimal_poses`` and
    ``select=False``: every reachable candidate as a calibration pose (for comparisons).
    ``workspace``: the joints of :func:`workspace_poses`, if they are already known (else
    computed when the selection needs them); ``progress`` hears what the plan is doing.
    Refused before any work: a model without finite, plausible joint limits, a home
    outside them, a plan too large (:func:`check_size`). The moves between the poses
    are not checked here: :func:`cellcal.campaign.plan_checks.moves_outside` says which
    leave the workspace box on the way (``cellcal plan`` prints them); the safety gate
    refuses them."""
    check_inputs(cfg, model, home_q)
    plan = _planned(cfg, model, home_q, target_offset, select, workspace, progress)
    return replace(plan, limits_deg=limits_deg(model))


def limits_deg(model: RobotModel) -> tuple[tuple[float, float], ...]:
    """The model's joint limits (deg, rounded at 1e-9°)."""
    lo, hi = model.limits
    return tuple(
        (round(float(np.degrees(a)), 9) + 0.0, round(float(np.degrees(b)), 9) + 0.0)
        for a, b in zip(lo, hi, strict=True)
    )


def _planned(
    cfg: CampaignConfig,
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    select: bool,
    workspace: Array | None,
    progress: Progress,
) -> Plan:
    """:func:`make_plan` once its inputs are checked."""
    if cfg.optimal_poses and select and workspace is None:
        workspace = workspace_poses(cfg, model, home_q, target_offset, progress=progress)
    rng = np.random.default_rng(cfg.seed)
    R0 = target_kinematics(model, home_q[None], target_offset, jacobian=False).R_flange[0]
    lo_box, hi_box = box(cfg)
    groups: list[tuple[str, str, Array, Array]] = []
    cube = cube_points(cfg)
    # drawn even when the candidates come from the workspace: the validation poses below
    # come from the same generator and must not change with the region
    cube_R = orientations(rng, R0, len(cube), cfg.orientation_variation_deg)
    turn = max(cfg.orientation_variation_deg, CANDIDATE_VARIATION_DEG)
    poses: list[PlannedPose] = []
    drawn = len(cube)
    if cfg.optimal_poses and cfg.region == WORKSPACE:
        region = draw_reachable(
            cfg,
            model,
            home_q,
            target_offset,
            np.random.default_rng([cfg.seed, 2]),
            REGION_CANDIDATES,
            turn,
        )
        drawn = region.drawn
        poses += [
            PlannedPose(k, CALIBRATION, WORKSPACE, p, q)
            for k, (p, q) in enumerate(zip(region.points, region.q, strict=True))
        ]
    else:
        if cfg.optimal_poses:
            # Candidates: each grid point at its plan orientation and at more seeded ones.
            more = np.random.default_rng([cfg.seed, 1])
            extra = CANDIDATE_ORIENTATIONS - 1
            cube_R = np.concatenate([cube_R, orientations(more, R0, extra * len(cube), turn)])
            cube = np.concatenate([cube, np.tile(cube, (extra, 1))])
            drawn = len(cube)
        groups.append((CALIBRATION, CUBE, cube, cube_R))
    c = np.asarray(cfg.cube_centre_mm)
    h = cfg.cube_edge_mm / 2.0
    inside = c + rng.uniform(-h, h, (cfg.validation_inside, 3))
    groups.append(
        (
            VALIDATION,
            CUBE,
            inside,
            orientations(rng, R0, len(inside), cfg.orientation_variation_deg),
        )
    )
    for k, centre in enumerate(cfg.validation_regions_mm, start=1):
        pts = _ball(
            rng, np.asarray(centre), cfg.validation_region_radius_mm, cfg.validation_per_region
        )
        groups.append(
            (
                VALIDATION,
                f"O{k}",
                pts,
                orientations(rng, R0, len(pts), cfg.orientation_variation_deg),
            )
        )

    unreachable: list[UnreachablePose] = []
    for role, region_name, pts, Rs in groups:
        if len(pts) == 0:
            continue
        q, ok = solve_group(model, home_q, target_offset, R0, pts, Rs)
        for p, qi, good in zip(pts, q, ok, strict=True):
            in_box = bool(np.all(p >= lo_box) and np.all(p <= hi_box))
            if not in_box:
                reason = "outside the workspace box"
                unreachable.append(UnreachablePose(role, region_name, p, reason))
            elif not good:
                reason = "no joint solution within the limits"
                unreachable.append(UnreachablePose(role, region_name, p, reason))
            else:
                poses.append(PlannedPose(len(poses), role, region_name, p, qi))
    if not cfg.optimal_poses:
        return Plan(tuple(poses), tuple(unreachable))
    reachable = sum(1 for p in poses if p.role == CALIBRATION)
    where = "drawn over the workspace box" if cfg.region == WORKSPACE else "in the cube"
    found = f"{reachable} reachable candidates of {drawn} {where} ({drawn - reachable} unreachable)"
    if not select or workspace is None:
        progress(found)
        return Plan(tuple(poses), tuple(unreachable), reachable, None, drawn)
    progress(f"{found}; choosing {cfg.optimal_poses} ({cfg.optimal_criterion}-optimal) …")
    return _optimal(cfg, poses, unreachable, model, home_q, target_offset, workspace, drawn)


def workspace_poses(
    cfg: CampaignConfig,
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    *,
    progress: Progress = _quiet,
) -> Array:
    """Joint readings (rad) of the workspace points the prediction is judged at, the
    unreachable ones left out. ``campaign.region = "cube"``: inside the cube and in the
    validation regions, drawn like the validation poses but from another seed.
    ``"workspace"``: :data:`REGION_POINTS` reachable poses drawn over the workspace box,
    turned as the validation poses are, from another seed than the candidates'."""
    check_inputs(cfg, model, home_q)
    if cfg.region == WORKSPACE:
        rng = np.random.default_rng([cfg.seed + WORKSPACE_SEED, 2])
        region = draw_reachable(
            cfg, model, home_q, target_offset, rng, REGION_POINTS, cfg.orientation_variation_deg
        )
        progress(
            f"{len(region.q)} reachable workspace points of {region.drawn} drawn to judge "
            "the prediction at"
        )
        return region.q
    points = cfg.model_copy(
        update={
            "seed": cfg.seed + WORKSPACE_SEED,
            "optimal_poses": 0,
            "validation_inside": WORKSPACE_INSIDE,
            "validation_per_region": WORKSPACE_PER_REGION,
        }
    )
    plan = make_plan(points, model, home_q, target_offset)
    return np.array([p.q for p in plan.poses if p.role == VALIDATION]).reshape(-1, model.dof)


def cell_seconds(q: Array, start: Array, speed_rad_s: float, dwell_s: float) -> float:
    """The time the poses ``q`` (N×n, rad, in order) take from ``start``: the dwell at
    each plus each move, its largest joint turn at ``speed_rad_s`` (an estimate that
    ignores acceleration and the controller's own motion profile)."""
    path = np.vstack([np.asarray(start, dtype=np.float64)[None], q])
    turns = np.abs(np.diff(path, axis=0)).max(axis=1) if len(q) else np.zeros(0)
    return float(turns.sum() / speed_rad_s + dwell_s * len(q))


def identification_jacobian(
    model: RobotModel, q: Array, target_offset: Array, also: Array | None = None
) -> tuple[Array, tuple[ParameterSpec, ...]]:
    """The identification Jacobian (N×3×P) at the poses ``q`` (rad) over every parameter
    a calibration estimates, sensor frame and target offset included, as the
    identification sets it up: the sensor frame's rotation about the centroid of the
    measured points (which moves the condition number, not how the D-criterion ranks
    sets of poses). With ``also``: those poses' rows follow, in the same parameters."""
    state = State(model, target_offset, np.eye(3), np.zeros(3), np.zeros(3))
    centroid = predict(state, q).mean(axis=0)
    state = State(model, target_offset, np.eye(3), np.zeros(3), centroid)
    specs = parameter_specs(model)
    rows = q if also is None or len(also) == 0 else np.concatenate([q, also])
    _, J = jacobian(state, rows, specs)
    return J, specs


def plan_identifiability(
    model: RobotModel, plan: Plan, target_offset: Array
) -> Identifiability | None:
    """What the plan's calibration poses identify (None without any): the parameters,
    those left at nominal and why, and the condition number of the column-scaled
    Jacobian of the identified set."""
    q = np.array([p.q for p in plan.poses if p.role == CALIBRATION])
    if len(q) == 0:
        return None
    J, specs = identification_jacobian(model, q, target_offset)
    return analyse_identifiability(J.reshape(-1, len(specs)), specs)


def identification_blocks(
    model: RobotModel, q: Array, target_offset: Array, workspace: Array | None = None
) -> tuple[Array, Array, tuple[str, ...]]:
    """Per pose, the identification Jacobian's 3×P block of the parameters these poses
    identify (sensor frame and target offset included), columns scaled to unit length
    over all poses; the same blocks at the ``workspace`` poses (J×3×P, J = 0 without);
    and those parameters' names."""
    J, specs = identification_jacobian(model, q, target_offset, workspace)
    n = len(q)
    keep = list(analyse_identifiability(J[:n].reshape(-1, len(specs)), specs).identified)
    G = J[:, :, keep]
    norms = np.linalg.norm(G[:n].reshape(-1, len(keep)), axis=0)
    out: Array = G / np.where(norms > 0, norms, 1.0)
    return out[:n], out[n:], tuple(specs[k].name for k in keep)


def expected_rms(
    model: RobotModel, q: Array, target_offset: Array, workspace: Array
) -> float | None:
    """The expected RMS prediction error at the workspace poses of a calibration from the
    poses ``q`` (rad), in units of the measurement noise σ per coordinate (√ of the mean
    prediction variance, linearised at the nominal model); None without poses."""
    if len(q) == 0 or len(workspace) == 0:
        return None
    G, H, _ = identification_blocks(model, q, target_offset, workspace)
    return prediction_rms(G, H, list(range(len(q))))


def _optimal(
    cfg: CampaignConfig,
    poses: list[PlannedPose],
    unreachable: list[UnreachablePose],
    model: RobotModel,
    home_q: Array,
    target_offset: Array,
    workspace: Array,
    drawn: int,
) -> Plan:
    """The plan with the campaign's optimal calibration poses of the candidates (D- or
    I-optimal), in a short tour from home, then the validation poses; unreachable
    candidates are not poses (``drawn`` counts them)."""
    candidates = [p for p in poses if p.role == CALIBRATION]
    if not candidates:
        if cfg.region == WORKSPACE:
            raise InputError(
                f"none of {drawn} poses drawn over the workspace box is reachable; check "
                "campaign.workspace_min_mm and workspace_max_mm"
            )
        raise InputError("no calibration candidate of the cube is reachable; check the cube")
    q = np.array([p.q for p in candidates])
    G, H, _ = identification_blocks(model, q, target_offset, workspace)
    n = cfg.optimal_poses
    if cfg.optimal_criterion == "I":
        if len(H) == 0:
            raise InputError("no workspace point is reachable to judge the prediction at")
        selection = i_optimal(G, H, n)
    else:
        selection = d_optimal(G, n)
        if len(H):
            selection = replace(selection, prediction_rms=prediction_rms(G, H, selection.chosen))
    chosen = [candidates[k] for k in selection.chosen]
    order = nearest_neighbour_order(np.array([p.q for p in chosen]), home_q)
    kept = [chosen[k] for k in order] + [p for p in poses if p.role != CALIBRATION]
    renumbered = tuple(
        PlannedPose(i, p.role, p.region, p.target_mm, p.q) for i, p in enumerate(kept)
    )
    left = tuple(u for u in unreachable if u.role != CALIBRATION)
    return Plan(renumbered, left, len(candidates), selection, drawn)
