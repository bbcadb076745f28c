"""A fit's estimates as a calibration reports them: each parameter's correction and its
standard uncertainty in display units (mm, deg), the sensor frames' uncertainties, and
the names ``--fix`` takes (earlier spellings read too)."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import replace

import numpy as np

from cellcal.calib.calibration_result import ParameterEstimate
from cellcal.calib.error_model import KINEMATIC_KINDS, ParameterSpec, State
from cellcal.calib.geometry import Array, skew, so3_log, wrap_deg
from cellcal.calib.identifiability import Identifiability
from cellcal.calib.robot_model import RobotModel
from cellcal.errors import InputError

#: Earlier spellings ``--fix`` still takes: the group ``tool`` and the names ``tool_x`` …
#: ``tool_rz`` (``:A`` for a target's group kept), now ``target_offset``, ``target_offset_x``,
#: ``target_rotation_x``.
_OLD_PREFIXES = (("tool_r", "target_rotation_"), ("tool_", "target_offset_"))


def current_name(item: str) -> str:
    if item == "tool":
        return "target_offset"
    for old, new in _OLD_PREFIXES:
        if item.startswith(old) and item[len(old) : len(old) + 1] in ("x", "y", "z"):
            return new + item[len(old) :]
    return item


def expand_fix(specs: tuple[ParameterSpec, ...], fix: Collection[str]) -> frozenset[str]:
    """Parameter names to pin: names, or the groups ``kinematics``, ``target_offset``
    (earlier spellings read: :data:`_OLD_PREFIXES`)."""
    names = {s.name for s in specs}
    out: set[str] = set()
    for item in map(current_name, fix):
        if item == "kinematics":  # the geometry and the error terms
            out |= {s.name for s in specs if s.kind in (*KINEMATIC_KINDS, "term")}
        elif item == "target_offset":
            out |= {s.name for s in specs if s.kind in ("target_offset", "target_rotation")}
        elif item in names:
            out.add(item)
        else:
            raise InputError(
                f"--fix {item}: no such parameter; choose from kinematics, target_offset, or "
                f"{', '.join(s.name for s in specs if not s.kind.startswith('frame'))}"
            )
    return frozenset(out)


def estimates(
    state: State,
    nominal: RobotModel,
    specs: tuple[ParameterSpec, ...],
    sel: tuple[ParameterSpec, ...],
    std: Array,
    ident: Identifiability,
) -> tuple[ParameterEstimate, ...]:
    """Every kinematic and target parameter of ``specs`` (frames and error terms left
    out): its correction to ``nominal`` and, when it was fitted (in ``sel``, whose
    standard uncertainties are ``std``), its uncertainty; else why it was not."""
    sel_index = {s.name: k for k, s in enumerate(sel)}
    out = []
    for i, sp in enumerate(specs):
        if sp.kind.startswith("frame") or sp.kind == "term":
            continue
        k = sel_index.get(sp.name)
        if sp.kind == "target_offset":
            value = float(state.target_offsets[sp.group, sp.axis])
        elif sp.kind == "target_rotation":
            assert state.target_rotations is not None
            value = math.degrees(float(so3_log(state.target_rotations[sp.group])[sp.axis]))
        else:
            value = sp.to_display(
                getattr(state.model.joints[sp.joint - 1], sp.kind)
                - getattr(nominal.joints[sp.joint - 1], sp.kind)
            )
            value = wrap_deg(value) if sp.is_angle else value
        sd = 0.0 if k is None else sp.to_display(float(std[k]))
        out.append(
            ParameterEstimate(
                sp.name,
                sp.kind,
                sp.joint,
                sp.unit,
                k is not None,
                value,
                sd,
                "" if k is not None else ident.reason(i),
            )
        )
    return tuple(out)


def frame_std(state: State, sel: tuple[ParameterSpec, ...], cov: Array, session: int = 0) -> Array:
    """Standard uncertainty of a session's T_sensor_base rotation vector and
    translation (at the sensor origin), from the covariance of the pivot
    parameterisation."""
    idx = [k for k, s in enumerate(sel) if s.kind.startswith("frame") and s.group == session]
    if len(idx) != 6:
        return np.full(6, np.nan)
    C = cov[np.ix_(idx, idx)]
    # t = E(ω)(t₀ − pivot) + pivot + δt  ⇒  ∂t/∂ω = −[t₀ − pivot]×, ∂t/∂δt = I.
    G = np.eye(6)
    G[3:6, 0:3] = -skew(state.ts[session] - state.pivots[session])
    out: Array = np.sqrt(np.clip(np.diag(G @ C @ G.T), 0.0, None))
    return out


def estimates_preview(
    state: State, nominal: RobotModel, sel: tuple[ParameterSpec, ...]
) -> list[tuple[str, str, float]]:
    """(name, unit, correction) of the identified kinematic parameters, display units."""
    out = []
    for sp in sel:
        if sp.kind in KINEMATIC_KINDS:
            j = sp.joint - 1
            delta = getattr(state.model.joints[j], sp.kind) - getattr(nominal.joints[j], sp.kind)
            out.append((sp.name, sp.unit, sp.to_display(delta)))
    return out


def with_term_sigma(state: State, sel: tuple[ParameterSpec, ...], std: Array) -> State:
    """``state`` with each fitted error term's coefficients' standard uncertainties
    (``std`` of ``sel``, internal units); a term held as it was keeps its own."""
    terms = state.model.terms
    if not terms or not any(sp.kind == "term" for sp in sel):
        return state
    sigma = [np.array(t.sigma, dtype=np.float64) for t in terms]
    for k, sp in enumerate(sel):
        if sp.kind == "term":
            sigma[sp.group][sp.index] = std[k]
    model = state.model.with_terms(
        tuple(
            t.with_coefficients(np.array(t.coefficients), s)
            for t, s in zip(terms, sigma, strict=True)
        )
    )
    return replace(state, model=model)
