"""Repeated reference poses: their repeatability and drift, against a known truth."""

from __future__ import annotations

import math

import numpy as np

from cellcal.calib.reference_repeats import reference_repeats
from cellcal.campaign.plan import CALIBRATION, VALIDATION, Plan, PlannedPose
from cellcal.campaign.reference_poses import REFERENCE, with_reference_poses


def test_a_known_drift_and_spread_are_measured() -> None:
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 4 * 3600.0, 40)
    rate = np.array([0.03, -0.04, 0.0])  # mm/h: 0.05 mm/h
    labels = tuple("ab"[k % 2] for k in range(len(t)))
    start = np.where(np.array(labels)[:, None] == "a", [500.0, 0.0, 900.0], [600.0, 10.0, 800.0])
    p = start + np.outer(t / 3600.0, rate) + rng.normal(0.0, 0.005, (len(t), 3))
    a, b = reference_repeats(labels, p, t)
    assert (a.label, a.n, b.label, b.n) == ("a", 20, "b", 20)
    for r in (a, b):
        assert abs(r.drift_mm_per_h - 0.05) < 3 * r.drift_sigma_mm_per_h + 1e-9
        assert r.drift_sigma_mm_per_h < 0.005
        assert 0.05 < r.repeatability_mm < 0.12  # the drift's spread over 4 h dominates
    (still,) = reference_repeats(("c",) * 2, p[:2], t[:2])
    assert math.isnan(still.drift_mm_per_h)  # two measurements: no trend


def test_reference_poses_open_close_and_punctuate_the_plan() -> None:
    poses = tuple(
        PlannedPose(
            i, CALIBRATION if i < 8 else VALIDATION, "cube", np.array([i, 0.0, 0.0]), np.zeros(6)
        )
        for i in range(10)
    )
    plan = with_reference_poses(Plan(poses, ()), 2, 4)
    roles = [p.role for p in plan.poses]
    assert [p.idx for p in plan.poses] == list(range(len(plan.poses)))
    assert roles[:2] == [REFERENCE] * 2 and roles[-2:] == [REFERENCE] * 2
    assert roles.count(REFERENCE) == 2 * 4  # first, after 4, after 8, after the last 2
    refs = {p.region: float(p.target_mm[0]) for p in plan.poses if p.role == REFERENCE}
    assert refs == {"ref1": 3.0, "ref2": 4.0}  # the calibration poses nearest their middle
    assert with_reference_poses(Plan(poses, ()), 0, 4).poses == poses
