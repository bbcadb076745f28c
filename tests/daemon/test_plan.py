"""The plan: properties that hold for any cube the robot can reach."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcal.calib.kinematics import target_kinematics
from cellcal.config import CampaignConfig
from cellcal.daemon.plan import CALIBRATION, VALIDATION, cube_points, make_plan
from cellcal.modelfiles import load_model

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
