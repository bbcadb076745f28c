"""What the error terms read of a campaign's stored poses: each pose's time, temperature
(the robot's joints' mean where it reports them, else a tracker's air) and planned
payload, and the repeated reference poses' repeatability and
drift."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.reference_repeats import ReferenceRepeat, reference_repeats
from cellcal.campaign.reference_poses import REFERENCE
from cellcal.store.database import PoseData


def with_pose_payloads(data: PoseData, payload_of: Mapping[int, float | None] | None) -> PoseData:
    """``data`` with each pose's planned payload (none planned: as it is)."""
    if not payload_of or all(v is None for v in payload_of.values()):
        return data
    kg = [payload_of.get(int(i)) for i in data.idx]
    return replace(data, payload_kg=np.array([np.nan if v is None else v for v in kg]))


def pose_conditions(data: PoseData, rows: Array) -> Conditions | None:
    """The time and air temperature of some poses, for error terms (a column only where
    every one of those poses has it)."""

    def column(values: Array | None) -> Array | None:
        if values is None or not np.isfinite(values[rows]).all():
            return None
        out: Array = values[rows]
        return out

    # the robot's own joints where it reports them, else the air a tracker measured in
    time_s = column(data.time_s)
    temperature_c = column(data.robot_temperature_c)
    if temperature_c is None:
        temperature_c = column(data.temperature_c)
    payload_kg = column(data.payload_kg)
    if time_s is None and temperature_c is None and payload_kg is None:
        return None
    return Conditions(time_s=time_s, temperature_c=temperature_c, payload_kg=payload_kg)


def repeats_of(data: PoseData, sensor: str) -> tuple[ReferenceRepeat, ...]:
    """The reference poses' repeatability and drift as ``sensor`` measured them (none
    without reference poses or without their times)."""
    rows = (np.array(data.role) == REFERENCE) & data.measured(sensor)
    if not rows.any() or data.time_s is None or not np.isfinite(data.time_s[rows]).all():
        return ()
    labels = tuple(str(r) for r in np.array(data.region)[rows])
    return reference_repeats(labels, data.mean[sensor][rows], data.time_s[rows])
