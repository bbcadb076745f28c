"""How far a model's error terms move its target: per term, over given poses — the size
a report shows and the loss a URDF export warns of."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_terms import TERM_NAMES, Conditions, Term
from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import RobotModel


@dataclass(frozen=True)
class TermEffect:
    """A term's (or, named ``all``, every term's) displacement of the target (mm): RMS
    and largest over the poses, and the joints it turns (0 for a drift)."""

    name: str
    joints: tuple[int, ...]
    rms_mm: float
    max_mm: float


def term_effects(
    model: RobotModel, target_offset: Array, q: Array, conditions: Conditions | None = None
) -> tuple[TermEffect, ...]:
    """Each of the model's terms' effect at the readings ``q`` (N×n, rad), in
    :data:`TERM_NAMES` order, then all of them together; empty without terms."""
    if not model.terms or not len(q):
        return ()
    bare = target_kinematics(model.geometry, q, target_offset, jacobian=False).p

    def effect(name: str, terms: tuple[Term, ...]) -> TermEffect:
        p = target_kinematics(
            model.with_terms(terms), q, target_offset, jacobian=False, conditions=conditions
        ).p
        d = np.linalg.norm(p - bare, axis=1)
        joints = tuple(sorted({t.joint for t in terms}))
        return TermEffect(name, joints, math.sqrt(float(np.mean(d**2))), float(d.max()))

    out = [
        effect(name, tuple(t for t in model.terms if t.name == name))
        for name in TERM_NAMES
        if any(t.name == name for t in model.terms)
    ]
    return (*out, effect("all", model.terms))


def readings_within_limits(model: RobotModel, n: int, seed: int = 0) -> Array:
    """n joint readings (rad) uniform within each joint's limits (a turn each way at most)."""
    lo, hi = model.limits
    lo, hi = np.maximum(lo, -math.pi), np.minimum(hi, math.pi)
    out: Array = np.random.default_rng(seed).uniform(lo, hi, (n, model.dof))
    return out
