"""Repeated reference poses: ``[campaign] reference_poses = N`` measures the N
calibration poses nearest the middle of the plan's targets first, then again after
every ``reference_every`` poses and at the end, as poses of role ``reference`` (regions
``ref1`` … ``refN``). They are not fitted: they measure repeatability and drift
directly (:mod:`cellcal.calib.reference_repeats`). With payload sessions they are
measured in each session, with its payload."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cellcal.campaign.plan import CALIBRATION, Plan, PlannedPose

REFERENCE = "reference"


def with_reference_poses(plan: Plan, count: int, every: int) -> Plan:
    """The plan with ``count`` reference poses measured at its start, after every
    ``every`` of its poses and at its end (count 0: the plan as it is)."""
    calibration = [p for p in plan.poses if p.role == CALIBRATION]
    if count <= 0 or not calibration:
        return plan
    targets = np.array([p.target_mm for p in calibration])
    middle = targets.mean(axis=0)
    nearest = np.argsort(np.linalg.norm(targets - middle, axis=1), kind="stable")[:count]
    refs = [
        replace(calibration[int(k)], role=REFERENCE, region=f"ref{i + 1}")
        for i, k in enumerate(nearest)
    ]
    ordered: list[PlannedPose] = list(refs)
    for start in range(0, len(plan.poses), every):
        ordered += plan.poses[start : start + every]
        ordered += refs
    return replace(plan, poses=tuple(replace(p, idx=i) for i, p in enumerate(ordered)))
