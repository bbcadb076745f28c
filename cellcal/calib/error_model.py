"""The error model: which parameters a calibration may estimate, and their Jacobian.

A measurement is the target position in the sensor's frame,

    m = T_sensor_base[s] · FK(q; geometry) · target_offset[t],

for the measurement's session s (a sensor set-up) and target t (e.g. one of three
SMRs); with a 6-DOF sensor also the target's orientation
R_sensor_base[s] · R_base_flange(q) · R_flange_target[t]. The parameters are, in
this order:

* per joint i: θᵢ, then dᵢ — or βᵢ where the row's axes are parallel (Hayati) — then
  aᵢ and αᵢ: corrections to the nominal geometry (mm, rad);
* per target, the target offset on the flange, ``tool_x``, ``tool_y``, ``tool_z`` (mm),
  and for 6-DOF measurements its orientation ``tool_rx/ry/rz`` (rad, a rotation vector
  applied in the flange frame); a target's parameters are named ``tool_x:NAME`` when
  there are several targets;
* per session, the sensor frame ``T_sensor_base``: a rotation vector
  ``frame_rx/ry/rz`` (rad, applied on the left, about the sensor's axes through a
  pivot — the centroid of the session's measurements — so that rotation and translation
  are not needlessly correlated) and a translation ``frame_x/y/z`` (mm); named
  ``frame_x:NAME`` when there are several sessions.

``paper_parameters=True`` gives the paper's set instead (θ, d, a, α for every row, no β).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.error_terms import Conditions, drift_parts, drift_variable, joint_regressors
from cellcal.calib.geometry import Array, so3_exp
from cellcal.calib.kinematics import ROW_PARAMS, TargetKinematics, chain_frames, target_kinematics
from cellcal.calib.robot_model import Joint, RobotModel
from cellcal.calib.rotations import rotvec_from_matrix

KINEMATIC_KINDS = ("theta", "d", "a", "alpha", "beta")


@dataclass(frozen=True)
class ParameterSpec:
    """One estimable parameter: its name (``a2``, ``beta3``, ``tool_x``, ``frame_rz``,
    ``tool_x:SMR2``), kind, joint (1-based, or 0), the unit it is shown in (``mm`` or
    ``deg``), and for target and frame parameters the target's or session's index."""

    name: str
    kind: str
    joint: int
    unit: str
    group: int = 0
    #: an error term's regressor (``group`` is the term's index in the model's terms)
    index: int = 0

    @property
    def is_angle(self) -> bool:
        return self.unit == "deg"

    @property
    def axis(self) -> int:
        """0, 1, 2 for the x, y, z of a target or frame parameter."""
        return "xyz".index(self.name.split(":")[0][-1])

    @property
    def display_factor(self) -> float:
        """Display units per internal unit: deg per rad (an angle, or an error term's
        turn per regressor unit: deg, deg/m, deg/kN·m), ppm per fraction (a drift's
        growth), 1 for mm."""
        if self.unit.startswith("deg"):
            return math.degrees(1.0)
        return 1e6 if self.unit.startswith("ppm") else 1.0

    def to_display(self, value: float) -> float:
        """Internal (mm, rad) to display (mm, deg)."""
        if self.unit.startswith("deg"):
            return math.degrees(value)
        return value * self.display_factor


#: Row indices (into a measurement set, or into a Groups' names).
Index = NDArray[np.intp]


@dataclass(frozen=True)
class Groups:
    """Which target and which session (sensor set-up) each measurement belongs to:
    ``target``/``session`` are N indices into ``targets``/``sessions`` (their names, in
    order of first appearance; ``("",)`` for a file without the column)."""

    target: Index
    session: Index
    targets: tuple[str, ...] = ("",)
    sessions: tuple[str, ...] = ("",)

    @classmethod
    def single(cls, n: int) -> Groups:
        return cls(np.zeros(n, dtype=np.intp), np.zeros(n, dtype=np.intp))

    @classmethod
    def of(
        cls, n: int, targets: Sequence[str] | None = None, sessions: Sequence[str] | None = None
    ) -> Groups:
        """Groups from per-row labels (None: one target, one session)."""

        def index(labels: Sequence[str] | None) -> tuple[Index, tuple[str, ...]]:
            if labels is None:
                return np.zeros(n, dtype=np.intp), ("",)
            names = tuple(dict.fromkeys(labels))
            pos = {k: i for i, k in enumerate(names)}
            return np.array([pos[v] for v in labels], dtype=np.intp), names

        t, tn = index(targets)
        s, sn = index(sessions)
        return cls(t, s, tn, sn)

    def subset(self, rows: Index) -> Groups:
        """The groups of some rows (the names stay, so parameters keep their meaning)."""
        return Groups(self.target[rows], self.session[rows], self.targets, self.sessions)


def label_index(
    n: int, labels: Sequence[str] | None, known: Sequence[str]
) -> tuple[Index, str | None]:
    """Each of n rows' index into ``known`` by its label (all 0 without labels), and the
    first label that is not known (None when every one is)."""
    if labels is None:
        return np.zeros(n, dtype=np.intp), None
    pos = {k: i for i, k in enumerate(known)}
    unknown = next((v for v in labels if v not in pos), None)
    if unknown is not None:
        return np.zeros(n, dtype=np.intp), unknown
    return np.array([pos[v] for v in labels], dtype=np.intp), None


def _label(base: str, names: tuple[str, ...], k: int) -> str:
    return base if len(names) == 1 else f"{base}:{names[k]}"


def parameter_specs(
    model: RobotModel,
    *,
    paper_parameters: bool = False,
    frame: bool = True,
    groups: Groups | None = None,
    orientation: bool = False,
) -> tuple[ParameterSpec, ...]:
    """The full, ordered parameter list of a model (kinematic, targets, frames)."""
    targets = groups.targets if groups is not None else ("",)
    sessions = groups.sessions if groups is not None else ("",)
    specs = []
    for i, par in enumerate(model.parallel, start=1):
        second = "beta" if par and not paper_parameters else "d"
        for kind in ("theta", second, "a", "alpha"):
            unit = "mm" if kind in ("d", "a") else "deg"
            specs.append(ParameterSpec(f"{kind}{i}", kind, i, unit))
    for g in range(len(targets)):
        specs += [
            ParameterSpec(_label(f"target_offset_{c}", targets, g), "target_offset", 0, "mm", g)
            for c in "xyz"
        ]
        if orientation:
            specs += [
                ParameterSpec(
                    _label(f"target_rotation_{c}", targets, g), "target_rotation", 0, "deg", g
                )
                for c in "xyz"
            ]
    specs += term_specs(model)
    if frame:
        for g in range(len(sessions)):
            specs += [
                ParameterSpec(_label(f"frame_r{c}", sessions, g), "frame_rot", 0, "deg", g)
                for c in "xyz"
            ]
            specs += [
                ParameterSpec(_label(f"frame_{c}", sessions, g), "frame_trans", 0, "mm", g)
                for c in "xyz"
            ]
    return tuple(specs)


def term_specs(model: RobotModel) -> list[ParameterSpec]:
    """One parameter per coefficient of the model's error terms, named
    ``harmonics2_sin1``, ``gravity3_R4x``, ``drift_scale``."""
    out = []
    for g, t in enumerate(model.terms):
        stem = t.name if t.name == "drift" else f"{t.name}{t.joint}"
        out += [
            ParameterSpec(f"{stem}_{r}", "term", t.joint, t.display_unit(k), g, k)
            for k, r in enumerate(t.regressors)
        ]
    return out


def _stack(a: Array, shape: tuple[int, ...]) -> Array:
    a = np.asarray(a, dtype=np.float64)
    out: Array = a[None] if a.ndim == len(shape) else a
    return out


@dataclass(frozen=True)
class State:
    """Geometry, target offsets and sensor frames, in mm and rad. Per target:
    ``tools`` (T×3) and, for 6-DOF fits, ``tool_rotations`` (T×3×3, R_flange_target); per session:
    ``Rs`` (S×3×3), ``ts`` (S×3) and ``pivots`` (S×3), the point (sensor frame) that
    frame rotations turn about. A single target's or session's arrays may be given
    unstacked; ``target_offset``, ``R``, ``t``, ``pivot`` are those of the first."""

    model: RobotModel
    target_offsets: Array
    Rs: Array
    ts: Array
    pivots: Array
    target_rotations: Array | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "target_offsets", _stack(self.target_offsets, (3,)))
        object.__setattr__(self, "Rs", _stack(self.Rs, (3, 3)))
        object.__setattr__(self, "ts", _stack(self.ts, (3,)))
        object.__setattr__(self, "pivots", _stack(self.pivots, (3,)))
        if self.target_rotations is not None:
            object.__setattr__(self, "target_rotations", _stack(self.target_rotations, (3, 3)))

    @property
    def target_offset(self) -> Array:
        out: Array = self.target_offsets[0]
        return out

    @property
    def R(self) -> Array:
        out: Array = self.Rs[0]
        return out

    @property
    def t(self) -> Array:
        out: Array = self.ts[0]
        return out

    @property
    def pivot(self) -> Array:
        out: Array = self.pivots[0]
        return out

    @property
    def T_sensor_base(self) -> Array:
        return self.frame(0)

    def frame(self, session: int) -> Array:
        """T_sensor_base of a session (4×4)."""
        T = np.eye(4)
        T[:3, :3] = self.Rs[session]
        T[:3, 3] = self.ts[session]
        return T


def _per_point(state: State, groups: Groups | None, n: int) -> tuple[Array, Array, Array]:
    """Per measurement: its session's R (N×3×3) and t (N×3), its target's offset (N×3)."""
    g = groups if groups is not None else Groups.single(n)
    return state.Rs[g.session], state.ts[g.session], state.target_offsets[g.target]


def predict(
    state: State, q: Array, groups: Groups | None = None, conditions: Conditions | None = None
) -> Array:
    """Target positions in the sensor frame (N×3, mm) for joint readings q (rad), at the
    measurements' ``conditions`` (for a model's error terms)."""
    q = np.atleast_2d(q)
    Rp, tp, target_offset = _per_point(state, groups, len(q))
    k = target_kinematics(state.model, q, target_offset, jacobian=False, conditions=conditions)
    out: Array = np.einsum("nij,nj->ni", Rp, k.p) + tp
    return out


def predict_orientation(state: State, q: Array, groups: Groups | None = None) -> Array:
    """Target orientations R_sensor_target (N×3×3) for joint readings q (rad)."""
    q = np.atleast_2d(q)
    g = groups if groups is not None else Groups.single(len(q))
    k = target_kinematics(state.model, q, np.zeros(3), jacobian=False)
    tR = state.target_rotations if state.target_rotations is not None else np.eye(3)[None]
    out: Array = state.Rs[g.session] @ k.R_flange @ tR[g.target]
    return out


def orientation_residuals(measured_R: Array, predicted_R: Array) -> Array:
    """Rotation vectors (N×3, rad, sensor frame) taking predicted onto measured."""
    out: Array = rotvec_from_matrix(measured_R @ np.swapaxes(predicted_R, 1, 2))
    return out


def jacobian(
    state: State,
    q: Array,
    specs: tuple[ParameterSpec, ...],
    groups: Groups | None = None,
    orientation: bool = False,
    conditions: Conditions | None = None,
) -> tuple[Array, Array]:
    """Predicted positions (N×3) and ∂m/∂parameters (N×3×P, sensor frame); with
    ``orientation`` N×6×P, rows 3–5 the angular velocity of the target's orientation."""
    g = groups if groups is not None else Groups.single(len(q))
    Rp, tp, target_offset = _per_point(state, g, len(q))
    kin = [col for col, sp in enumerate(specs) if sp.kind in KINEMATIC_KINDS]
    terms = [col for col, sp in enumerate(specs) if sp.kind == "term"]
    k = target_kinematics(
        state.model,
        q,
        target_offset,
        jacobian=bool(kin or terms),
        angular=orientation,
        conditions=conditions,
    )
    one = len(state.Rs) == 1  # one session: one rotation for every row
    R0 = state.Rs[0]
    m = (k.p @ R0.T if one else np.einsum("nij,nj->ni", Rp, k.p)) + tp
    N = len(q)
    J = np.zeros((N, 6 if orientation else 3, len(specs)))

    def turn(v: Array) -> Array:  # base-frame vectors (N×3×K) into the sensor frame
        out: Array = np.matmul(R0, v) if one else np.matmul(Rp, v)
        return out

    if kin:
        c = [5 * (specs[col].joint - 1) + ROW_PARAMS.index(specs[col].kind) for col in kin]
        J[:, :3, kin] = turn(k.J_rows[:, :, c])
        if orientation:
            assert k.W_rows is not None
            J[:, 3:, kin] = turn(k.W_rows[:, :, c])
    if terms:
        _term_columns(state, q, specs, terms, k, turn, J, orientation, conditions)
    flange = turn(k.R_flange)  # columns: the flange axes in the sensor frame
    for col, sp in enumerate(specs):
        if sp.kind in KINEMATIC_KINDS or sp.kind == "term":
            continue
        if sp.kind in ("target_offset", "target_rotation"):
            rows = g.target == sp.group
            v = flange[:, :, sp.axis]
            if sp.kind == "target_offset":
                J[rows, :3, col] = v[rows]
            elif orientation:
                J[rows, 3:, col] = v[rows]
            continue
        rows = g.session == sp.group
        e = np.zeros(3)
        e[sp.axis] = 1.0
        if sp.kind == "frame_rot":  # e × (m − pivot)
            v = m[rows] - state.pivots[sp.group]
            a, b = (sp.axis + 1) % 3, (sp.axis + 2) % 3
            J[rows, a, col] = -v[:, b]
            J[rows, b, col] = v[:, a]
            if orientation:
                J[rows, 3:, col] = e
        else:
            J[rows, :3, col] = e
    return m, J


def _term_columns(
    state: State,
    q: Array,
    specs: tuple[ParameterSpec, ...],
    cols: list[int],
    k: TargetKinematics,
    turn: Callable[[Array], Array],
    J: Array,
    orientation: bool,
    conditions: Conditions | None,
) -> None:
    """The error terms' columns of J: a joint term's coefficient turns its joint by its
    regressor (∂m/∂θᵢ · r); a drift's moves the position by its variable × (direction, or
    the position itself for the growth)."""
    model = state.model
    chain = (
        chain_frames(model, q)
        if any(model.terms[specs[c].group].name in ("gravity", "compliance") for c in cols)
        else None
    )
    regressors: dict[int, Array] = {}
    for col in cols:
        sp = specs[col]
        term = model.terms[sp.group]
        if term.is_joint_term:
            if sp.group not in regressors:
                regressors[sp.group] = joint_regressors(
                    term, q, chain, model.mass_model, conditions
                )
            r = regressors[sp.group][:, sp.index]
            J[:, :3, col] = turn(k.J_rows[:, :, 5 * (sp.joint - 1), None])[:, :, 0] * r[:, None]
            if orientation:
                assert k.W_rows is not None
                W = turn(k.W_rows[:, :, 5 * (sp.joint - 1), None])[:, :, 0]
                J[:, 3:, col] = W * r[:, None]
            continue
        x = drift_variable(term, conditions, len(q))
        v, scale = drift_parts(term)
        which = term.regressors[sp.index]
        if which != "scale":
            e = np.zeros((len(q), 3, 1))
            e[:, "xyz".index(which), 0] = x
            J[:, :3, col] = turn(e)[:, :, 0]
        else:
            p_geometry = (k.p - np.outer(x, v)) / (1.0 + scale * x)[:, None]
            J[:, :3, col] = turn((p_geometry * x[:, None])[:, :, None])[:, :, 0]


def apply(state: State, specs: tuple[ParameterSpec, ...], delta: Array) -> State:
    """The state moved by ``delta`` (internal units) along ``specs``."""
    joints = list(state.model.joints)
    target_offsets = state.target_offsets.copy()
    S, T = len(state.Rs), len(state.target_offsets)
    omega = np.zeros((S, 3))
    dt = np.zeros((S, 3))
    target_omega = np.zeros((T, 3))
    coefficients = [np.array(t.coefficients) for t in state.model.terms]
    for sp, v in zip(specs, delta, strict=True):
        if sp.kind == "term":
            coefficients[sp.group][sp.index] += v
        elif sp.kind in KINEMATIC_KINDS:
            j = joints[sp.joint - 1]
            joints[sp.joint - 1] = replace(j, **{sp.kind: getattr(j, sp.kind) + float(v)})
        elif sp.kind == "target_offset":
            target_offsets[sp.group, sp.axis] += v
        elif sp.kind == "target_rotation":
            target_omega[sp.group, sp.axis] += v
        elif sp.kind == "frame_rot":
            omega[sp.group, sp.axis] += v
        else:
            dt[sp.group, sp.axis] += v
    E = np.stack([so3_exp(w) for w in omega])
    # m' = E (m − pivot) + pivot + dt for every predicted m of the session.
    Rs = E @ state.Rs
    ts = np.einsum("sij,sj->si", E, state.ts - state.pivots) + state.pivots + dt
    target_rotations = state.target_rotations
    if target_rotations is not None:
        target_rotations = np.stack([so3_exp(w) for w in target_omega]) @ target_rotations
    model = state.model.with_joints(tuple(joints))
    if coefficients:
        model = model.with_terms(
            tuple(t.with_coefficients(c) for t, c in zip(model.terms, coefficients, strict=True))
        )
    return State(
        model,
        target_offsets,
        Rs,
        ts,
        state.pivots,
        target_rotations,
    )


def joint_errors(nominal: RobotModel, calibrated: RobotModel) -> list[tuple[Joint, Joint]]:
    """Pairs (nominal, calibrated) of each row, for reports."""
    return list(zip(nominal.joints, calibrated.joints, strict=True))
