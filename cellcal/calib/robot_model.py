"""Robot kinematic models: standard (DH) and Craig's modified (MDH) Denavit–Hartenberg.

A model is a frozen value: its joints' geometry in mm and radians, joint limits, the
nominal target offset on the flange, and which rows use Hayati's β in place of d
because two consecutive joint axes are (nearly) parallel. Models are read from the
TOML format of the public contract by :func:`model_from_dict`; the file itself is read
at the edge (``cellcal.files.models``).

Per joint i, the transform from frame i−1 to frame i is a product of elementary
transforms; ``q`` is the joint reading, θ its offset:

* ``dh``:  Rz(θᵢ + qᵢ) · Tz(dᵢ) · Tx(aᵢ) · Rx(αᵢ) · Ry(βᵢ)
* ``mdh``: Rx(αᵢ₋₁) · Ry(βᵢ₋₁) · Tx(aᵢ₋₁) · Rz(θᵢ + qᵢ) · Tz(dᵢ)   (the row of joint i holds
  αᵢ₋₁, aᵢ₋₁, dᵢ, θᵢ, as in Craig)

β is zero in every nominal model; it exists so that a small tilt between parallel axes
has a parameter that is small too (in DH, d of a parallel pair is undefined: any tilt
moves the common normal arbitrarily far).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from cellcal.calib.error_terms import MassModel, Term, term_from_dict, term_to_dict
from cellcal.calib.geometry import Array, wrap_deg
from cellcal.errors import InputError

Convention = Literal["dh", "mdh"]
#: Consecutive axes closer than this are treated as parallel (Hayati's β replaces d).
PARALLEL_AXES_DEG = 1.0

#: A model that drives a robot has joint limits within this (deg) of the zero reading:
#: the widest industrial axes (UR e-Series, KUKA's A4/A6) turn ±350..360°; a larger
#: range (a URDF's ±1e9, a "continuous" joint, a typo) is no robot's. An axis that turns
#: farther is given the ±360° it needs for calibration poses.
MAX_LIMIT_DEG = 360.0
#: How a model is given limits, for the messages that refuse one without them.
LIMITS_HOW = (
    "give each joint's limits from the robot's data sheet: min and max (deg) in each "
    '[[joint]] of a model TOML, or in a URDF type="revolute" with <limit lower=… upper=…> '
    '(rad; a "continuous" joint has none)'
)

_JOINT_KEYS = {
    "a",
    "alpha",
    "d",
    "theta",
    "beta",
    "min",
    "max",
    "scale",
    "couple",
    "mass_kg",
    "com_mm",
}
_TOP_KEYS = {"name", "convention", "joint", "tool", "description", "term", "payload_com_mm"}


class ModelError(InputError):
    """A robot model that cannot be used (bad TOML values, unknown keys, missing rows)."""


@dataclass(frozen=True)
class Joint:
    """One row of the table. Lengths mm, angles rad; limits apply to the joint reading.
    The joint angle is ``scale`` × its reading (+ ``couple_factor`` × the reading of joint
    ``couple_joint``, 1-based, 0 for none), then θ is added."""

    a: float
    alpha: float
    d: float
    theta: float
    beta: float = 0.0
    q_min: float = -math.inf
    q_max: float = math.inf
    scale: float = 1.0
    couple_joint: int = 0
    couple_factor: float = 0.0
    #: the link's mass (kg) and centre of mass (mm, in the joint's link frame — the frame
    #: after its row); None: not given (no mass model)
    mass_kg: float | None = None
    com_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RobotModel:
    """A serial robot with revolute joints. ``tool_xyz`` is the nominal target offset in
    the flange frame (mm), a starting guess only. ``parallel[i]`` is True where row i uses β
    in place of d."""

    name: str
    convention: Convention
    joints: tuple[Joint, ...]
    target_offset_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    parallel: tuple[bool, ...] = ()
    #: error terms beyond geometry (cellcal.calib.error_terms), in TERM_NAMES order
    terms: tuple[Term, ...] = ()
    #: the payload's centre of mass in the flange frame (mm)
    payload_com_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.parallel:
            object.__setattr__(self, "parallel", detect_parallel(self.convention, self.joints))

    @property
    def target_offset(self) -> Array:
        """The nominal target offset as an array (mm)."""
        return np.array(self.target_offset_xyz, dtype=np.float64)

    @property
    def dof(self) -> int:
        return len(self.joints)

    @property
    def limits(self) -> tuple[Array, Array]:
        """Joint-reading limits (rad): two arrays of length ``dof``."""
        lo = np.array([j.q_min for j in self.joints])
        hi = np.array([j.q_max for j in self.joints])
        return lo, hi

    def joint_outside_limits(self, q: Array, slack: float = 1e-9) -> int | None:
        """The index of the first joint reading of ``q`` (rad) outside its limits by more
        than ``slack`` (rad), or None."""
        lo, hi = self.limits
        bad = np.flatnonzero((q < lo - slack) | (q > hi + slack))
        return int(bad[0]) if len(bad) else None

    @property
    def reading_matrix(self) -> Array:
        """A (n×n): joint angles (before θ) = A · readings. Identity unless a joint has a
        ``scale`` or a ``couple``; a coupling to a joint beyond this model is ignored."""
        n = self.dof
        A = np.zeros((n, n))
        for i, j in enumerate(self.joints):
            A[i, i] = j.scale
            if 0 < j.couple_joint <= n:
                A[i, j.couple_joint - 1] += j.couple_factor
        return A

    @property
    def maps_readings(self) -> bool:
        """True when a joint's angle is not simply its reading."""
        return any(j.scale != 1.0 or j.couple_joint for j in self.joints)

    def joint_angles(self, q: Array) -> Array:
        """Joint angles before θ (N×n, rad) for readings ``q`` (N×n, rad)."""
        if not self.maps_readings:
            return q
        out: Array = q @ self.reading_matrix.T
        return out

    def with_joints(self, joints: tuple[Joint, ...]) -> RobotModel:
        """The same model with other geometry (same β rows)."""
        return replace(self, joints=joints)

    def with_terms(self, terms: tuple[Term, ...]) -> RobotModel:
        """The same geometry with other error terms."""
        return replace(self, terms=terms)

    @property
    def mass_model(self) -> MassModel | None:
        """Every link's mass and centre of mass and the payload's, or None when a joint
        has no mass."""
        masses = [j.mass_kg for j in self.joints]
        if any(m is None for m in masses):
            return None
        return MassModel(
            np.array(masses, dtype=np.float64),
            np.array([j.com_mm for j in self.joints], dtype=np.float64),
            np.array(self.payload_com_mm, dtype=np.float64),
        )

    @property
    def geometry(self) -> RobotModel:
        """The model without its error terms."""
        return self if not self.terms else self.with_terms(())


def detect_parallel(convention: str, joints: tuple[Joint, ...]) -> tuple[bool, ...]:
    """Rows whose twist makes two consecutive joint axes parallel within 1°.

    DH row i (i < n) carries αᵢ between axes i and i+1; the flange row is not between two
    joint axes. MDH row i (i > 1) carries αᵢ₋₁ between axes i−1 and i.
    """
    tol = math.sin(math.radians(PARALLEL_AXES_DEG))
    n = len(joints)
    flags = []
    for i, j in enumerate(joints):
        between_axes = i < n - 1 if convention == "dh" else i > 0
        flags.append(between_axes and abs(math.sin(j.alpha)) < tol)
    return tuple(flags)


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelError(f"{where}: expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ModelError(f"{where}: not finite")
    return x


def model_from_dict(data: Mapping[str, object], source: str = "model") -> RobotModel:
    """Build a model from the contract's TOML structure (mm, deg); strict about keys."""
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ModelError(f"{source}: unknown key {unknown[0]!r}")
    name = data.get("name", "unnamed")
    if not isinstance(name, str) or not name:
        raise ModelError(f"{source}: name must be a non-empty string")
    convention = data.get("convention", "dh")
    if convention not in ("dh", "mdh"):
        raise ModelError(f'{source}: convention must be "dh" or "mdh", got {convention!r}')
    rows = data.get("joint")
    if not isinstance(rows, list) or not rows:
        raise ModelError(f"{source}: needs one [[joint]] table per joint")
    joints = []
    for i, row in enumerate(rows, start=1):
        where = f"{source}: joint {i}"
        if not isinstance(row, dict):
            raise ModelError(f"{where}: must be a table")
        bad = sorted(set(row) - _JOINT_KEYS)
        if bad:
            raise ModelError(f"{where}: unknown key {bad[0]!r}")
        missing = [k for k in ("a", "alpha", "d", "theta") if k not in row]
        if missing:
            raise ModelError(f"{where}: missing {', '.join(missing)}")
        lo = _number(row["min"], f"{where}.min") if "min" in row else -math.inf
        hi = _number(row["max"], f"{where}.max") if "max" in row else math.inf
        if lo >= hi:
            raise ModelError(f"{where}: min must be below max")
        scale = _number(row.get("scale", 1.0), f"{where}.scale")
        if scale == 0.0:
            raise ModelError(f"{where}.scale: must not be 0 (−1 reverses an axis)")
        couple_joint, couple_factor = _couple(row.get("couple"), where, i, len(rows))
        joints.append(
            Joint(
                a=_number(row["a"], f"{where}.a"),
                alpha=math.radians(_number(row["alpha"], f"{where}.alpha")),
                d=_number(row["d"], f"{where}.d"),
                theta=math.radians(_number(row["theta"], f"{where}.theta")),
                beta=math.radians(_number(row.get("beta", 0.0), f"{where}.beta")),
                q_min=math.radians(lo) if math.isfinite(lo) else lo,
                q_max=math.radians(hi) if math.isfinite(hi) else hi,
                scale=scale,
                couple_joint=couple_joint,
                couple_factor=couple_factor,
                mass_kg=_mass(row.get("mass_kg"), f"{where}.mass_kg"),
                com_mm=_xyz(row.get("com_mm", [0.0, 0.0, 0.0]), f"{where}.com_mm"),
            )
        )
    target_offset = (0.0, 0.0, 0.0)
    if "tool" in data:
        t = data["tool"]
        if not isinstance(t, dict) or set(t) - {"xyz"}:
            raise ModelError(f"{source}: [tool] takes only xyz = [x, y, z] (mm)")
        xyz = t.get("xyz")
        if not isinstance(xyz, list) or len(xyz) != 3:
            raise ModelError(f"{source}: tool.xyz must be [x, y, z] in mm")
        x, y, z = (_number(v, f"{source}: tool.xyz") for v in xyz)
        target_offset = (x, y, z)
    conv: Convention = "dh" if convention == "dh" else "mdh"
    terms = _terms(data.get("term", []), source, len(joints))
    model = RobotModel(
        name=name,
        convention=conv,
        joints=tuple(joints),
        target_offset_xyz=target_offset,
        terms=terms,
        payload_com_mm=_xyz(
            data.get("payload_com_mm", [0.0, 0.0, 0.0]), f"{source}: payload_com_mm"
        ),
    )
    if model.maps_readings and abs(np.linalg.det(model.reading_matrix)) < 1e-9:
        raise ModelError(
            f"{source}: the joints' scale and couple make two joint angles depend on the "
            "same readings (the reading → angle map is singular)"
        )
    return model


def limits_problem(model: RobotModel) -> str | None:
    """What is wrong with the model's joint limits for driving a robot, naming the joint
    (None when every joint has finite limits, min < max, within ±:data:`MAX_LIMIT_DEG`)."""
    for i, j in enumerate(model.joints, start=1):
        lo, hi = math.degrees(j.q_min), math.degrees(j.q_max)
        if math.isnan(lo) or math.isnan(hi) or (math.isinf(lo) and math.isinf(hi)):
            return f"joint {i} has no limits"
        if not math.isfinite(lo):
            return f"joint {i} has no lower limit (min)"
        if not math.isfinite(hi):
            return f"joint {i} has no upper limit (max)"
        if lo >= hi:
            return f"joint {i}'s limits {lo:.6g}..{hi:.6g}° are not min < max"
        if max(abs(lo), abs(hi)) > MAX_LIMIT_DEG + 1e-9:
            return (
                f"joint {i}'s limits {lo:.6g}..{hi:.6g}° go beyond ±{MAX_LIMIT_DEG:g}°, "
                "which no robot's joint range does"
            )
    return None


def require_limits(model: RobotModel, source: str) -> None:
    """Refuse (one line naming the joint) a model whose joint limits cannot keep a robot
    safe: every use that drives a robot or plans its moves calls this; reading a model
    to predict or calibrate does not."""
    problem = limits_problem(model)
    if problem is not None:
        raise ModelError(f"{source}: {problem}; a model that drives a robot must {LIMITS_HOW}")


def _couple(value: object, where: str, i: int, n: int) -> tuple[int, float]:
    """``couple = { joint = J, factor = F }`` of joint ``i`` → (J, F); (0, 0.0) if absent."""
    if value is None:
        return 0, 0.0
    if not isinstance(value, dict) or set(value) != {"joint", "factor"}:
        raise ModelError(f"{where}.couple: must be {{ joint = J, factor = F }}")
    joint = value["joint"]
    if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= n:
        raise ModelError(f"{where}.couple.joint: must be a joint number 1..{n}")
    if joint == i:
        raise ModelError(f"{where}.couple.joint: a joint cannot couple to itself (use scale)")
    return joint, _number(value["factor"], f"{where}.couple.factor")


def _mass(value: object, where: str) -> float | None:
    if value is None:
        return None
    m = _number(value, where)
    if not 0.0 <= m <= 10000.0:
        raise ModelError(f"{where}: a link's mass in kg, 0 to 10000 (grams?)")
    return m


def _xyz(value: object, where: str) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise ModelError(f"{where}: must be [x, y, z] in mm")
    x, y, z = (_number(v, where) for v in value)
    return (x, y, z)


def _terms(value: object, source: str, n: int) -> tuple[Term, ...]:
    """``[[term]]`` tables: error terms beyond geometry (cellcal.calib.error_terms)."""
    if not isinstance(value, list):
        raise ModelError(f"{source}: [[term]] must be an array of tables")
    out: list[Term] = []
    for i, row in enumerate(value, start=1):
        try:
            t = term_from_dict(row, f"{source}: term {i}", n)
        except ValueError as e:
            raise ModelError(str(e)) from None
        if any(o.name == t.name and o.joint == t.joint for o in out):
            raise ModelError(f"{source}: term {i}: a second {t.name} term of joint {t.joint}")
        out.append(t)
    return tuple(out)


def _deg(rad: float) -> float:
    """Degrees, rounded at 1e-12° so that 15° read and written stays 15°."""
    return round(math.degrees(rad), 12) + 0.0


def _angle(rad: float) -> float:
    """A geometric angle in degrees, wrapped to (−180°, 180°]."""
    return wrap_deg(_deg(rad))


def model_to_dict(model: RobotModel) -> dict[str, object]:
    """The contract's TOML structure (mm, deg) of a model. ``beta`` (an optional key that
    cellcal adds to the format) is written only where it is not zero; θ, α, β are wrapped
    to (−180°, 180°]."""
    rows: list[dict[str, object]] = []
    for j in model.joints:
        row: dict[str, object] = {
            "a": j.a,
            "alpha": _angle(j.alpha),
            "d": j.d,
            "theta": _angle(j.theta),
        }
        if j.beta != 0.0:
            row["beta"] = _angle(j.beta)
        if math.isfinite(j.q_min):
            row["min"] = _deg(j.q_min)
        if math.isfinite(j.q_max):
            row["max"] = _deg(j.q_max)
        if j.scale != 1.0:
            row["scale"] = j.scale
        if j.couple_joint:
            row["couple"] = {"joint": j.couple_joint, "factor": j.couple_factor}
        if j.mass_kg is not None:
            row["mass_kg"] = j.mass_kg
            row["com_mm"] = list(j.com_mm)
        rows.append(row)
    out: dict[str, object] = {"name": model.name, "convention": model.convention, "joint": rows}
    if any(model.target_offset_xyz):
        out["tool"] = {"xyz": list(model.target_offset_xyz)}
    if any(model.payload_com_mm):
        out["payload_com_mm"] = list(model.payload_com_mm)
    if model.terms:
        out["term"] = [term_to_dict(t) for t in model.terms]
    return out
