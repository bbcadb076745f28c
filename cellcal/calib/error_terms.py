"""Error terms beyond the kinematic parameters: what they are and how they are evaluated.

A term is a small, named correction a model carries besides its geometry:

* joint terms add to a joint's angle Δθᵢ = Σₖ cₖ·rₖ(q, …), each coefficient cₖ (rad
  internally, deg in files) times a known regressor rₖ:

  - ``gravity``: the deflection of a joint that carries the arm's weight. The torque
    about joint i of a mass m at a point fixed in link k is linear in m and in m × its
    centre of mass: ``axis_i · ((R_k e_c) × ĝ)`` for c = x, y, z (``R{k}{c}``,
    dimensionless) and ``axis_i · ((o_k − p_i) × ĝ)`` (``o{k}``, metres), where ĝ is
    gravity's direction, −z of the base (a floor-mounted robot), ``R_k``/``o_k`` the frame
    of link k and ``p_i`` a point on joint i's axis. Each coefficient is a compliance ×
    a mass moment, not a stiffness; the fit keeps the identifiable combinations.
  - ``harmonics``: ``sin1``, ``cos1``, ``sin2``, ``cos2`` of the joint's reading
    (eccentricity and ellipticity of its transmission), and ``sin{k}``, ``cos{k}`` at an
    order k a transmission's stage turns per joint turn, where the data show one
    (:mod:`cellcal.calib.cyclic_search`), within the range of readings
    the calibration measured (``range_deg``; none: every reading) and held at its ends
    beyond: over a range
    much shorter than a turn, a harmonic fits an offset, a scale and a bend of the
    reading, which no one may extrapolate.

  - ``compliance``: a joint's physical compliance (deg per kN·m) times the gravity
    torque about it (``tau``, kN·m) of the links it carries and the payload, from the
    model's mass model (each link's ``mass_kg`` and ``com_mm``, the payload's mass per
    measurement and ``payload_com_mm``); a joint driven together with another (a
    ``couple``) also yields to that joint's torque (``tau{j}``).

  - ``ratio``: a transmission's ratio error (a pulley's or a gear's radius, a cable's
    stretch along its run, an encoder's scale): the joint turns ``1 + k`` times what it
    reads. The regressor ``q`` is the reading (rad), less its mean over the
    calibration's poses (the geometry's θ holds an offset); ``k`` is written in %. It
    holds over any range: a ratio does not change along the reading.

* ``drift`` (joint 0): a slow change with the measurement's time (hours since the
  campaign's start) or temperature (°C above the campaign's first): the positions grow
  about the base origin by ``scale`` (ppm per hour or per °C) and shift by ``x``,
  ``y``, ``z`` (mm per hour or per °C, base frame). Growing every length in proportion
  scales every position about the base origin, exactly.

The regressors of a joint term need the chain's frames; :mod:`cellcal.calib.kinematics`
computes them and adds the terms' angles before the forward kinematics, so every use of
a model with terms includes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array

#: The terms a calibration may add, in the order they are tried and written.
TERM_NAMES = ("gravity", "compliance", "harmonics", "drift", "ratio")
HARMONICS = ("sin1", "cos1", "sin2", "cos2")
RATIO = ("q",)
DRIFT = ("x", "y", "z", "scale")
#: The drift's variables: a column of the measurements, and its unit in files.
DRIFT_VARIABLES = {"time_s": "h", "temperature_c": "°C"}
GRAVITY_DIRECTION = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class Conditions:
    """Per measurement, what the terms beyond geometry read: seconds since the
    campaign's start, temperature (°C) and payload (kg); None where not measured."""

    time_s: Array | None = None
    temperature_c: Array | None = None
    payload_kg: Array | None = None

    def subset(self, rows: NDArray[np.intp]) -> Conditions:
        def cut(a: Array | None) -> Array | None:
            return None if a is None else a[rows]

        return Conditions(cut(self.time_s), cut(self.temperature_c), cut(self.payload_kg))

    def column(self, name: str) -> Array | None:
        out: Array | None = getattr(self, name)
        return out


@dataclass(frozen=True)
class Term:
    """One term of a model: ``name`` (one of :data:`TERM_NAMES`), the ``joint`` it turns
    (1-based; 0 for ``drift``), its regressors' names, the coefficients (internal units:
    rad per regressor unit; for drift mm per unit and a fraction per unit) and their
    standard uncertainties (same units; NaN where unknown). ``variable``/``reference``: a
    drift's column and the value at which it is zero; a compliance's ``reference`` is the
    payload (kg) of measurements that give none."""

    name: str
    joint: int
    regressors: tuple[str, ...]
    coefficients: tuple[float, ...]
    sigma: tuple[float, ...] = ()
    variable: str = ""
    reference: float = 0.0
    #: a harmonic's range of readings (rad), beyond which it is held at its ends
    bounds: tuple[float, float] = (-math.inf, math.inf)
    #: each regressor's mean over the calibration's poses, taken off it (empty: none), so
    #: that the term adds no mean turn to its joint: the geometry's θ holds that, and the
    #: geometry alone (a URDF) is as near the model as it can be
    centre: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not self.sigma:
            object.__setattr__(self, "sigma", (math.nan,) * len(self.coefficients))

    @property
    def is_joint_term(self) -> bool:
        return self.name != "drift"

    def display_unit(self, k: int) -> str:
        """The unit a coefficient is shown and written in."""
        if self.name == "drift":
            per = DRIFT_VARIABLES.get(self.variable, "h")
            return f"ppm/{per}" if self.regressors[k] == "scale" else f"mm/{per}"
        if self.name == "gravity" and self.regressors[k].startswith("o"):
            return "deg/m"
        if self.name == "compliance":
            return "deg/kN·m"
        if self.name == "ratio":
            return "%"
        return "deg"

    def to_display(self, k: int, value: float) -> float:
        if self.name == "drift":
            return value * 1e6 if self.regressors[k] == "scale" else value
        if self.name == "ratio":
            return value * 100.0
        return math.degrees(value)

    def from_display(self, k: int, value: float) -> float:
        if self.name == "drift":
            return value * 1e-6 if self.regressors[k] == "scale" else value
        if self.name == "ratio":
            return value / 100.0
        return math.radians(value)

    def with_coefficients(self, coefficients: Array, sigma: Array | None = None) -> Term:
        s = self.sigma if sigma is None else tuple(float(v) for v in sigma)
        return replace(self, coefficients=tuple(float(v) for v in coefficients), sigma=s)


#: Standard gravity (m/s²).
G_N_PER_KG = 9.80665


@dataclass(frozen=True)
class MassModel:
    """Every link's mass (kg, n) and centre of mass (mm, n×3, in its link frame), and the
    payload's centre of mass (mm, in the flange frame)."""

    mass_kg: Array
    com_mm: Array
    payload_com_mm: Array


@dataclass(frozen=True)
class ChainFrames:
    """Per pose, every link's frame after its row (``R``: N×n×3×3, ``o``: N×n×3, mm) and
    every joint's axis (``axis``: N×n×3) and a point on it (``point``: N×n×3, mm), in
    the base frame."""

    R: Array
    o: Array
    axis: Array
    point: Array


def gravity_regressors(joint: int, n: int) -> tuple[str, ...]:
    """The regressors of a gravity term of joint ``joint`` (1-based) of an n-joint arm:
    every link it carries."""
    return tuple(
        name for k in range(joint, n + 1) for name in (f"R{k}x", f"R{k}y", f"R{k}z", f"o{k}")
    )


def joint_torques(frames: ChainFrames, mass: MassModel, payload_kg: Array) -> Array:
    """The gravity torque about every joint (N×n, kN·m) of the links it carries and a
    payload of ``payload_kg`` (N) at the flange."""
    N, n = frames.o.shape[:2]
    com = frames.o + np.einsum("nkij,kj->nki", frames.R, mass.com_mm)  # N×n×3, mm
    payload = frames.o[:, -1] + frames.R[:, -1] @ mass.payload_com_mm
    force = G_N_PER_KG * GRAVITY_DIRECTION  # per kg
    out = np.zeros((N, n))
    for i in range(n):
        lever = (com[:, i:] - frames.point[:, i, None]) / 1000.0  # m
        moment = np.cross(lever, force) * mass.mass_kg[i:, None]
        total = moment.sum(axis=1)
        total += np.cross((payload - frames.point[:, i]) / 1000.0, force) * payload_kg[:, None]
        out[:, i] = np.einsum("ni,ni->n", frames.axis[:, i], total)
    result: Array = out / 1000.0
    return result


def compliance_regressors(joint: int, coupled: tuple[int, ...]) -> tuple[str, ...]:
    """A compliance term's regressors: its own torque and its coupled joints'."""
    return ("tau", *(f"tau{j}" for j in coupled))


def payload_of(term: Term, conditions: Conditions | None, n: int) -> Array:
    """Each measurement's payload (kg): its column, else the calibration's."""
    col = None if conditions is None else conditions.payload_kg
    return np.full(n, term.reference) if col is None else col


def joint_regressors(
    term: Term,
    q: Array,
    frames: ChainFrames | None,
    mass: MassModel | None = None,
    conditions: Conditions | None = None,
) -> Array:
    """The regressors (N×K) of a joint term at readings ``q`` (N×n, rad), less their
    ``centre``."""
    raw = _raw_regressors(term, q, frames, mass, conditions)
    if term.centre:
        raw = raw - np.array(term.centre)
    return raw


def _raw_regressors(
    term: Term,
    q: Array,
    frames: ChainFrames | None,
    mass: MassModel | None,
    conditions: Conditions | None,
) -> Array:
    i = term.joint - 1
    cols = []
    if term.name == "compliance":
        assert frames is not None and mass is not None, "compliance needs frames and masses"
        tau = joint_torques(frames, mass, payload_of(term, conditions, len(q)))
        for name in term.regressors:
            cols.append(tau[:, i if name == "tau" else int(name[3:]) - 1])
        return np.stack(cols, axis=1)
    if term.name == "ratio":  # its one regressor, q
        return q[:, i : i + 1]
    for name in term.regressors:
        if term.name == "harmonics":
            order = int(name[3:])
            f = np.sin if name.startswith("sin") else np.cos
            cols.append(f(order * np.clip(q[:, i], *term.bounds)))
            continue
        assert frames is not None, "gravity regressors need the chain's frames"
        k = int(name[1:-1] if name.startswith("R") else name[1:]) - 1
        if name.startswith("R"):
            v = np.cross(frames.R[:, k, :, "xyz".index(name[-1])], GRAVITY_DIRECTION)
        else:
            v = np.cross((frames.o[:, k] - frames.point[:, i]) / 1000.0, GRAVITY_DIRECTION)
        cols.append(np.einsum("ni,ni->n", frames.axis[:, i], v))
    return np.stack(cols, axis=1) if cols else np.zeros((len(q), 0))


def needs_frames(terms: tuple[Term, ...]) -> bool:
    return any(t.name in ("gravity", "compliance") for t in terms)


def joint_deltas(
    terms: tuple[Term, ...],
    q: Array,
    frames: ChainFrames | None,
    mass: MassModel | None = None,
    conditions: Conditions | None = None,
) -> Array:
    """Δθ (N×n, rad) the joint terms add to the joints' angles."""
    out = np.zeros(q.shape)
    for t in terms:
        if t.is_joint_term and t.coefficients:
            r = joint_regressors(t, q, frames, mass, conditions)
            out[:, t.joint - 1] += r @ np.array(t.coefficients)
    return out


def drift_variable(term: Term, conditions: Conditions | None, n: int) -> Array:
    """The drift's variable per pose (hours, or °C above its reference); zero where the
    conditions do not give it (the campaign's start)."""
    col = None if conditions is None else conditions.column(term.variable)
    if col is None:
        return np.zeros(n)
    if term.variable == "time_s":
        out: Array = col / 3600.0
        return out
    return col - term.reference


def drift_of(terms: tuple[Term, ...]) -> Term | None:
    return next((t for t in terms if t.name == "drift"), None)


def drift_parts(term: Term) -> tuple[Array, float]:
    """A drift's shift v (mm per unit, base frame) and growth s (fraction per unit); a
    regressor it does not have is zero."""
    c = dict(zip(term.regressors, term.coefficients, strict=True))
    return np.array([c.get(a, 0.0) for a in "xyz"]), c.get("scale", 0.0)


def apply_drift(p: Array, term: Term, conditions: Conditions | None) -> Array:
    """Positions (N×3, base frame) after the drift: p·(1 + s·x) + v·x."""
    x = drift_variable(term, conditions, len(p))
    v, scale = drift_parts(term)
    out: Array = p * (1.0 + scale * x)[:, None] + np.outer(x, v)
    return out


def term_from_dict(row: object, where: str, n: int) -> Term:
    """A ``[[term]]`` table (display units) as a Term; ValueError with the reason."""
    if not isinstance(row, dict):
        raise ValueError(f"{where}: must be a table")
    keys = {
        "name",
        "joint",
        "regressors",
        "coefficients",
        "units",
        "sigma",
        "variable",
        "range_deg",
        "centre",
    }
    bad = sorted(set(row) - keys - {"reference"})
    if bad:
        raise ValueError(f"{where}: unknown key {bad[0]!r}")
    name, joint = row.get("name"), row.get("joint", 0)
    if name not in TERM_NAMES:
        raise ValueError(f"{where}: name must be one of {', '.join(TERM_NAMES)}, got {name!r}")
    if name == "drift":
        if joint != 0:
            raise ValueError(f"{where}: a drift has joint = 0")
        allowed: tuple[str, ...] = DRIFT
    else:
        if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= n:
            raise ValueError(f"{where}: joint must be a joint number 1..{n}")
        if name == "compliance":
            others = tuple(j for j in range(1, n + 1) if j != joint)
            allowed = compliance_regressors(joint, others)
        else:
            allowed = {"harmonics": HARMONICS, "ratio": RATIO}.get(
                str(name), gravity_regressors(joint, n)
            )
    regs = row.get("regressors")
    if name == "harmonics" and isinstance(regs, list):
        # a cyclic error at a transmission's own order: sin{k}, cos{k}, k up to 360
        allowed = tuple(dict.fromkeys((*allowed, *(r for r in regs if _cyclic_name(r)))))
    if not isinstance(regs, list) or not regs or any(r not in allowed for r in regs):
        raise ValueError(f"{where}: regressors must be a list of {', '.join(allowed)}")
    if len(set(regs)) != len(regs):
        raise ValueError(f"{where}: a regressor is listed twice")
    variable = str(row.get("variable", "time_s" if name == "drift" else ""))
    if name == "drift" and variable not in DRIFT_VARIABLES:
        raise ValueError(f"{where}: variable must be one of {', '.join(DRIFT_VARIABLES)}")
    shell = Term(str(name), int(joint), tuple(regs), (0.0,) * len(regs), variable=variable)

    def numbers(key: str, required: bool) -> list[float]:
        v = row.get(key)
        if v is None and not required:
            return [math.nan] * len(regs)
        if not isinstance(v, list) or len(v) != len(regs):
            raise ValueError(f"{where}: {key} must list one number per regressor")
        if any(isinstance(x, bool) or not isinstance(x, int | float) for x in v):
            raise ValueError(f"{where}: {key} must be numbers")
        return [float(x) for x in v]

    coefficients = numbers("coefficients", True)
    if not all(math.isfinite(c) for c in coefficients):
        raise ValueError(f"{where}: coefficients must be finite")
    units = row.get("units")
    expected = [shell.display_unit(k) for k in range(len(regs))]
    if units != expected:
        raise ValueError(f"{where}: units must be {expected} (got {units!r})")
    sigma = numbers("sigma", False)
    reference = row.get("reference", 0.0)
    if isinstance(reference, bool) or not isinstance(reference, int | float):
        raise ValueError(f"{where}: reference must be a number")
    bounds = (-math.inf, math.inf)
    if name == "harmonics" and "range_deg" in row:
        span = row.get("range_deg")
        items: list[object] = span if isinstance(span, list) else []
        values = [float(v) for v in items if not isinstance(v, bool) and isinstance(v, int | float)]
        if len(items) != 2 or len(values) != 2 or not -720.0 <= values[0] < values[1] <= 720.0:
            raise ValueError(f"{where}: range_deg must be [lo, hi], the readings it holds for")
        bounds = (math.radians(values[0]), math.radians(values[1]))
    centre: tuple[float, ...] = ()
    if "centre" in row:
        if name not in ("harmonics", "gravity", "ratio"):
            raise ValueError(f"{where}: only harmonics, gravity and ratio terms have a centre")
        centre = tuple(numbers("centre", True))
    return replace(
        shell,
        coefficients=tuple(shell.from_display(k, c) for k, c in enumerate(coefficients)),
        sigma=tuple(shell.from_display(k, c) for k, c in enumerate(sigma)),
        reference=float(reference),
        bounds=bounds,
        centre=centre,
    )


def _cyclic_name(name: object) -> bool:
    """``sin{k}`` or ``cos{k}`` for an order k of 1 to 360."""
    if not isinstance(name, str) or name[:3] not in ("sin", "cos") or not name[3:].isdigit():
        return False
    return 1 <= int(name[3:]) <= 360 and not name[3:].startswith("0")


def cyclic(order: int) -> tuple[str, str]:
    """The regressors of a cyclic error of order ``order`` (k turns per joint turn)."""
    return f"sin{order}", f"cos{order}"


def term_to_dict(term: Term) -> dict[str, object]:
    """A Term as a ``[[term]]`` table (display units)."""
    k = range(len(term.regressors))
    out: dict[str, object] = {
        "name": term.name,
        "joint": term.joint,
        "regressors": list(term.regressors),
        "coefficients": [term.to_display(i, term.coefficients[i]) for i in k],
        "units": [term.display_unit(i) for i in k],
    }
    if all(math.isfinite(v) for v in term.sigma):
        out["sigma"] = [term.to_display(i, term.sigma[i]) for i in k]
    if term.name == "drift":
        out["variable"] = term.variable
        out["reference"] = term.reference
    if term.name == "compliance":
        out["reference"] = term.reference  # the payload (kg) where the data give none
    if term.name == "harmonics" and all(math.isfinite(b) for b in term.bounds):
        out["range_deg"] = [math.degrees(b) for b in term.bounds]
    if term.centre:
        out["centre"] = list(term.centre)  # the regressors' own units (1, m)
    return out
