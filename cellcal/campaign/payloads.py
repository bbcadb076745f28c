"""Payload sessions: ``[campaign] payloads_kg = [0.0, 5.0]`` measures the plan once per
payload, in that order, so that a compliance term can be told from the arm's own mass
moments (``cellcal.calib.term_choice``).

The campaign starts with the first payload mounted. Before the first pose of the next
payload the acquisition stops, records a ``payload-change`` event with the instruction,
and the campaign is ``paused``; resuming it (``cellcal run --resume``, or ``cellcal
campaign resume`` in the service) is the operator's word that the payload is mounted,
recorded as a ``payload`` event. A campaign interrupted within a session goes on with
the payload of its last stored pose. In mock mode the simulated cell is handed the
payload the operator would have mounted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.campaign.plan import Plan

PAYLOAD_CHANGE = "payload-change"
PAYLOAD = "payload"


def with_payloads(plan: Plan, payloads_kg: Sequence[float]) -> Plan:
    """The plan's poses once per payload, in order (none given: the plan as it is)."""
    if not payloads_kg:
        return plan
    n = len(plan.poses)
    poses = tuple(
        replace(pose, idx=k * n + i, payload_kg=float(p))
        for k, p in enumerate(payloads_kg)
        for i, pose in enumerate(plan.poses)
    )
    return replace(plan, poses=poses)


def pose_payloads(payloads_kg: Sequence[float], n_poses: int, idx: Array) -> Array | None:
    """Each pose's payload (kg) from its plan index: session ``idx // (n_poses / k)``."""
    if not payloads_kg:
        return None
    per = max(n_poses // len(payloads_kg), 1)
    session = np.minimum(np.asarray(idx, dtype=int) // per, len(payloads_kg) - 1)
    out: Array = np.asarray(payloads_kg, dtype=np.float64)[session]
    return out


def instruction(payload_kg: float) -> str:
    """What the operator is asked to do before the next session."""
    return (
        f"mount the {payload_kg:g} kg payload (its centre of mass where the robot model's "
        "payload_com_mm says, in the flange frame; tell the controller its new load), "
        "then resume"
    )


def mounted_payload(
    plan: Plan, done: Sequence[int] | set[int], events: Sequence[Mapping[str, Any]]
) -> tuple[float | None, bool]:
    """The payload mounted as an acquisition (re)starts, and whether this start is the
    operator's word that it was just mounted (a resume after a ``payload-change``)."""
    todo = [p for p in plan.poses if p.idx not in done]
    if not todo or todo[0].payload_kg is None:
        return None, False
    if not done:
        return todo[0].payload_kg, False
    asked = [e for e in events if e["kind"] in (PAYLOAD_CHANGE, PAYLOAD)]
    if asked and asked[-1]["kind"] == PAYLOAD_CHANGE:
        return todo[0].payload_kg, True
    last = max(done)
    stored = next(p for p in plan.poses if p.idx == last)
    return stored.payload_kg, False
