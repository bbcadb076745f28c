"""A URDF's inertials as a robot model's mass model (for the compliance error term):
each joint's body as Pinocchio merges it — its link and every link fixed to it — becomes
that joint's ``mass_kg`` and ``com_mm`` in the model's link frame."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from cellcal.calib.kinematics import chain_frames
from cellcal.calib.robot_model import RobotModel


def with_inertials(model: RobotModel, pm: Any, d: Any, chain: list[int]) -> RobotModel:
    """``model`` (derived from Pinocchio's ``pm``, whose data ``d`` hold the zero
    readings' placements; ``chain``: its joints' ids, base to flange) with the file's
    inertials as its mass model; unchanged when the file gives no mass (all zero)."""
    masses = [float(pm.inertias[j].mass) for j in chain]
    if not any(m > 0 for m in masses):
        return model
    frames = chain_frames(model, np.zeros((1, len(chain))))  # the zero readings, as d
    joints = []
    for k, (j, row) in enumerate(zip(chain, model.joints, strict=True)):
        com_base = np.asarray(d.oMi[j].act(pm.inertias[j].lever), dtype=np.float64) * 1000.0
        com = frames.R[0, k].T @ (com_base - frames.o[0, k])
        joints.append(
            replace(row, mass_kg=masses[k], com_mm=(float(com[0]), float(com[1]), float(com[2])))
        )
    return model.with_joints(tuple(joints))
