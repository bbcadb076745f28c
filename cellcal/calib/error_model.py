"""The error model: which parameters a calibration may estimate, and their Jacobian.

A measurement is the target position in the instrument's frame,

    m = T_instrument_base · FK(q; geometry) · tool,

and the parameters are, in this order:

* per joint i: θᵢ, then dᵢ — or βᵢ where the row's axes are parallel (Hayati) — then
  aᵢ and αᵢ: corrections to the nominal geometry (mm, rad);
* the target offset on the flange, ``tool_x``, ``tool_y``, ``tool_z`` (mm);
* the instrument frame ``T_instrument_base``: a rotation vector ``frame_rx/ry/rz``
  (rad, applied on the left, about the instrument's axes through a pivot — the centroid
  of the measurements — so that rotation and translation are not needlessly
  correlated) and a translation ``frame_x/y/z`` (mm).

``paper_parameters=True`` gives the paper's set instead (θ, d, a, α for every row, no β).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from cellcal.calib.geometry import Array, so3_exp
from cellcal.calib.kinematics import ROW_PARAMS, target_kinematics
from cellcal.calib.robot_model import Joint, RobotModel

KINEMATIC_KINDS = ("theta", "d", "a", "alpha", "beta")


@dataclass(frozen=True)
class ParameterSpec:
    """One estimable parameter: its name (``a2``, ``beta3``, ``tool_x``, ``frame_rz``),
    kind, joint (1-based, or 0), and the unit it is shown in (``mm`` or ``deg``)."""

    name: str
    kind: str
    joint: int
    unit: str

    @property
    def is_angle(self) -> bool:
        return self.unit == "deg"

    def to_display(self, value: float) -> float:
        """Internal (mm, rad) to display (mm, deg)."""
        return math.degrees(value) if self.is_angle else value


def parameter_specs(
    model: RobotModel, *, paper_parameters: bool = False, frame: bool = True
) -> tuple[ParameterSpec, ...]:
    """The full, ordered parameter list of a model (kinematic, tool, frame)."""
    specs = []
    for i, par in enumerate(model.parallel, start=1):
        second = "beta" if par and not paper_parameters else "d"
        for kind in ("theta", second, "a", "alpha"):
            unit = "mm" if kind in ("d", "a") else "deg"
            specs.append(ParameterSpec(f"{kind}{i}", kind, i, unit))
    specs += [ParameterSpec(f"tool_{c}", "tool", 0, "mm") for c in "xyz"]
    if frame:
        specs += [ParameterSpec(f"frame_r{c}", "frame_rot", 0, "deg") for c in "xyz"]
        specs += [ParameterSpec(f"frame_{c}", "frame_trans", 0, "mm") for c in "xyz"]
    return tuple(specs)


@dataclass(frozen=True)
class State:
    """Geometry, target offset and instrument frame (R, t), in mm and rad; ``pivot`` is
    the point (instrument frame) that frame rotations turn about."""

    model: RobotModel
    tool: Array
    R: Array
    t: Array
    pivot: Array

    @property
    def T_instrument_base(self) -> Array:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T


def predict(state: State, q: Array) -> Array:
    """Target positions in the instrument frame (N×3, mm) for joint readings q (rad)."""
    k = target_kinematics(state.model, q, state.tool, jacobian=False)
    out: Array = k.p @ state.R.T + state.t
    return out


def jacobian(state: State, q: Array, specs: tuple[ParameterSpec, ...]) -> tuple[Array, Array]:
    """Predicted positions (N×3) and ∂m/∂parameters (N×3×P), instrument frame."""
    k = target_kinematics(state.model, q, state.tool)
    pb = k.p
    m = pb @ state.R.T + state.t
    N = len(q)
    J = np.empty((N, 3, len(specs)))
    Rm = state.R
    for col, sp in enumerate(specs):
        if sp.kind in KINEMATIC_KINDS:
            J[:, :, col] = k.J_rows[:, :, 5 * (sp.joint - 1) + ROW_PARAMS.index(sp.kind)] @ Rm.T
        elif sp.kind == "tool":
            axis = "xyz".index(sp.name[-1])
            J[:, :, col] = k.R_flange[:, :, axis] @ Rm.T
        elif sp.kind == "frame_rot":
            e = np.zeros(3)
            e["xyz".index(sp.name[-1])] = 1.0
            J[:, :, col] = np.cross(e, m - state.pivot)
        else:
            J[:, :, col] = 0.0
            J[:, "xyz".index(sp.name[-1]), col] = 1.0
    return m, J


def apply(state: State, specs: tuple[ParameterSpec, ...], delta: Array) -> State:
    """The state moved by ``delta`` (internal units) along ``specs``."""
    joints = list(state.model.joints)
    tool = state.tool.copy()
    omega = np.zeros(3)
    dt = np.zeros(3)
    for sp, v in zip(specs, delta, strict=True):
        if sp.kind in KINEMATIC_KINDS:
            j = joints[sp.joint - 1]
            joints[sp.joint - 1] = replace(j, **{sp.kind: getattr(j, sp.kind) + float(v)})
        elif sp.kind == "tool":
            tool["xyz".index(sp.name[-1])] += v
        elif sp.kind == "frame_rot":
            omega["xyz".index(sp.name[-1])] += v
        else:
            dt["xyz".index(sp.name[-1])] += v
    E = so3_exp(omega)
    # m' = E (m − pivot) + pivot + dt for every predicted m.
    R = E @ state.R
    t = E @ (state.t - state.pivot) + state.pivot + dt
    return State(state.model.with_joints(tuple(joints)), tool, R, t, state.pivot)


def joint_errors(nominal: RobotModel, calibrated: RobotModel) -> list[tuple[Joint, Joint]]:
    """Pairs (nominal, calibrated) of each row, for reports."""
    return list(zip(nominal.joints, calibrated.joints, strict=True))
