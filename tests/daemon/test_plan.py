"""The plan: properties that hold for any cube the robot can reach, and poses drawn over
the workspace box."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcal.calib.kinematics import target_kinematics
from cellcal.campaign import plan_region
from cellcal.campaign.plan import (
    CALIBRATION,
    VALIDATION,
    cube_points,
    make_plan,
    workspace_poses,
)
from cellcal.campaign.plan_region import REGION_CANDIDATES, REGION_POINTS, draw_reachable
from cellcal.config import CampaignConfig
from cellcal.errors import InputError
from cellcal.files.models import load_model

MODEL = load_model("kuka-kr5-arc").model
HOME = np.radians([0.0, -30.0, 40.0, 0.0, -20.0, 0.0])
TOOL = np.array([25.0, -40.0, 130.0])


def _check(plan, cfg):
    idx = [p.idx for p in plan.poses]
    assert idx == list(range(len(plan.poses)))
    q = np.array([p.q for p in plan.poses])
    lo, hi = MODEL.limits
    assert ((q >= lo - 1e-12) & (q <= hi + 1e-12)).all()
    reached = target_kinematics(MODEL, q, TOOL, jacobian=False).p
    np.testing.assert_allclose(reached, np.array([p.target_mm for p in plan.poses]), atol=1e-5)
    box_lo, box_hi = np.array(cfg.workspace_min_mm), np.array(cfg.workspace_max_mm)
    for p in plan.poses:
        assert (p.target_mm >= box_lo).all() and (p.target_mm <= box_hi).all()


def test_default_plan_is_the_papers_cube_plus_validation():
    cfg = CampaignConfig()
    plan = make_plan(cfg, MODEL, HOME, TOOL)
    _check(plan, cfg)
    assert plan.count(CALIBRATION) == 80
    cube = [p for p in plan.poses if p.role == CALIBRATION]
    assert np.ptp([p.target_mm for p in cube], axis=0) == pytest.approx([200, 200, 200])
    # Nothing is dropped silently: planned + unreachable = asked for.
    asked = 80 + cfg.validation_inside + cfg.validation_per_region * len(cfg.validation_regions_mm)
    assert len(plan.poses) + len(plan.unreachable) == asked
    regions = {p.region for p in plan.poses if p.role == VALIDATION}
    assert "cube" in regions and {"O1", "O2", "O3", "O4"} <= regions
    # The same inputs give the same plan.
    assert make_plan(cfg, MODEL, HOME, TOOL).digest == plan.digest


def test_serpentine_order_moves_one_grid_step_at_a_time():
    cfg = CampaignConfig(grid=[3, 4, 5])
    pts = cube_points(cfg)
    assert len(pts) == 60
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert steps.max() == pytest.approx(200 / 2)  # the x spacing of 3 points: 100 mm


def test_fixed_orientation_and_varied_orientation():
    fixed = make_plan(CampaignConfig(orientation_variation_deg=0.0), MODEL, HOME, TOOL)
    q = np.array([p.q for p in fixed.poses if p.role == CALIBRATION])
    R = target_kinematics(MODEL, q, TOOL, jacobian=False).R_flange
    assert np.abs(R - R[0]).max() < 1e-9
    varied = make_plan(CampaignConfig(orientation_variation_deg=30.0), MODEL, HOME, TOOL)
    q = np.array([p.q for p in varied.poses if p.role == CALIBRATION])
    R = target_kinematics(MODEL, q, TOOL, jacobian=False).R_flange
    assert np.abs(R - R[0]).max() > 0.1


def test_workspace_box_and_unreachable_poses_are_reported():
    cfg = CampaignConfig(
        workspace_max_mm=[2500.0, 2500.0, 1050.0],
        validation_regions_mm=[[1500.0, 1500.0, 600.0]],  # in the box, beyond the reach
        validation_region_radius_mm=100.0,
    )
    plan = make_plan(cfg, MODEL, HOME, TOOL)
    reasons = {(u.region, u.reason) for u in plan.unreachable}
    assert ("cube", "outside the workspace box") in reasons
    assert ("O1", "no joint solution within the limits") in reasons
    assert all(p.target_mm[2] <= 1050.0 for p in plan.poses)


@settings(max_examples=15, deadline=None)
@given(
    cx=st.floats(600, 850),
    cy=st.floats(-200, 200),
    cz=st.floats(800, 1100),
    edge=st.floats(50, 250),
    n=st.integers(2, 4),
    vary=st.floats(0, 30),
    seed=st.integers(0, 2**16),
)
def test_any_reachable_cube_gives_a_consistent_plan(cx, cy, cz, edge, n, vary, seed):
    cfg = CampaignConfig(
        cube_centre_mm=[cx, cy, cz],
        cube_edge_mm=edge,
        grid=[n, n, n],
        orientation_variation_deg=vary,
        validation_inside=5,
        validation_per_region=2,
        seed=seed,
    )
    plan = make_plan(cfg, MODEL, HOME, TOOL)
    _check(plan, cfg)
    assert len(plan.poses) + len(plan.unreachable) == n**3 + 5 + 2 * 5


#: A box about the robot's front, as a cell would set it (mm).
BOX = {"workspace_min_mm": [400.0, -900.0, 300.0], "workspace_max_mm": [1100.0, 900.0, 1300.0]}


def test_the_workspace_region_chooses_from_reachable_poses_drawn_over_the_box():
    cfg = CampaignConfig(optimal_poses=12, region="workspace", **BOX)
    plan = make_plan(cfg, MODEL, HOME, TOOL)
    _check(plan, cfg)
    cal = [p for p in plan.poses if p.role == CALIBRATION]
    assert len(cal) == 12 and {p.region for p in cal} == {"workspace"}
    # Chosen from REGION_CANDIDATES reachable ones; the unreachable draws are counted.
    assert plan.candidates == REGION_CANDIDATES and plan.drawn > plan.candidates
    assert plan.selection is not None and len(set(plan.selection.chosen)) == 12
    targets = np.array([p.target_mm for p in cal])
    assert np.ptp(targets, axis=0).min() > 300  # spread over the box, not a cube
    # The validation poses are the cube plan's, whatever the region: reports compare.
    cube = make_plan(CampaignConfig(optimal_poses=12, **BOX), MODEL, HOME, TOOL)
    np.testing.assert_array_equal(
        [p.q for p in plan.poses if p.role == VALIDATION],
        [p.q for p in cube.poses if p.role == VALIDATION],
    )
    assert [(u.region, u.reason) for u in plan.unreachable] == [
        (u.region, u.reason) for u in cube.unreachable if u.role == VALIDATION
    ]
    assert make_plan(cfg, MODEL, HOME, TOOL).digest == plan.digest  # seeded
    # The expected error is judged at other reachable poses drawn over the same box.
    judged = workspace_poses(cfg, MODEL, HOME, TOOL)
    assert judged.shape == (REGION_POINTS, 6)
    at = target_kinematics(MODEL, judged, TOOL, jacobian=False).p
    assert (at >= np.array(BOX["workspace_min_mm"]) - 1e-6).all()
    assert (at <= np.array(BOX["workspace_max_mm"]) + 1e-6).all()
    assert not np.isin(np.round(judged, 9), np.round([p.q for p in cal], 9)).all(axis=1).any()


def test_without_optimal_poses_the_region_only_moves_where_the_error_is_judged():
    cfg = CampaignConfig(region="workspace", **BOX)
    assert (
        make_plan(cfg, MODEL, HOME, TOOL).digest
        == make_plan(CampaignConfig(**BOX), MODEL, HOME, TOOL).digest
    )


def test_drawing_does_not_depend_on_how_many_poses_are_solved_at_once(monkeypatch):
    cfg = CampaignConfig(**BOX)

    def draw():
        return draw_reachable(cfg, MODEL, HOME, TOOL, np.random.default_rng(5), 40, 60.0)

    first = draw()
    monkeypatch.setattr(plan_region, "REGION_FIRST_BATCH", 7)
    again = draw()
    assert first.drawn == again.drawn and len(first.q) == 40
    np.testing.assert_array_equal(first.q, again.q)
    np.testing.assert_array_equal(first.points, again.points)


def test_a_box_the_robot_cannot_reach_is_refused(monkeypatch):
    monkeypatch.setattr(plan_region, "REGION_MAX_DRAWS", 50)
    cfg = CampaignConfig(
        optimal_poses=12,
        region="workspace",
        workspace_min_mm=[3000.0, 3000.0, 0.0],
        workspace_max_mm=[3500.0, 3500.0, 500.0],
    )
    with pytest.raises(InputError, match="none of 50 poses drawn over the workspace box"):
        make_plan(cfg, MODEL, HOME, TOOL)
