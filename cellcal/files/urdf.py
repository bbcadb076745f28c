"""Robot models as URDF, out and in (the edge: ``calib`` stays free of files).

Out: each row of the model's table is A_i · Rz(s_i·q_i) · B_i with fixed A and B — DH:
A = I, B = Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i) Ry(β_i); modified DH (Craig): A = Rx(α) Ry(β)
Tx(a), B = Rz(θ) Tz(d) — so joint i's origin is B_{i−1} · A_i and its axis z, signed by
the joint's scale (±1), and the joint's URDF value is the controller's reading. Putting
θ in B (first, on the left of the next row's twist) keeps every origin's pitch small, so
roll-pitch-yaw never meets its singularity where DH rows turn by 90° twice; every
origin is rebuilt from what is written and must agree to 1e-12.

In: the text is screened first (``urdf_input``: no DTD or entity, joints and links
bounded), then Pinocchio parses it, every failure one line; the serial chain of
revolute joints from the root to the end frame (``tool0``, else ``flange``, else the
last joint's link) becomes a modified-DH table by the common normals of consecutive
joint axes at the zero readings, with Hayati's β where consecutive axes are parallel.
Its inertials become the model's mass model (each joint body's mass and centre of
mass, for the compliance error term). The end frame is the model's flange frame,
orientation included (the last row's θ, and scale −1 where its z is against the last
axis), so that a target offset read back names the point it named; an end frame no DH
table can end on (tilted off the last axis, or its origin off it) is said in one warning
line, the model then ending on the nearest frame that one can, with the end frame's
origin as the model's ``[tool]`` offset. The result is checked against Pinocchio's own
kinematics of the file at random readings, and refused when they differ.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.calib.geometry import Array, invert, so3_log
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.robot_model import PARALLEL_AXES_DEG, Joint, RobotModel
from cellcal.config_earlier import Warn, warn_on_stderr
from cellcal.errors import FileFormatError, InputError
from cellcal.files.text import read_text
from cellcal.files.urdf_inertials import with_inertials
from cellcal.files.urdf_input import MAX_BYTES, first_line, pinocchio_model, screen

#: A rebuilt origin may differ from the intended one by this much (rotation, and m).
ROUND_TRIP = 1e-12


def _rx(t: float) -> Array:
    c, s = math.cos(t), math.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _ry(t: float) -> Array:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _rz(t: float) -> Array:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _t(x: float, y: float, z: float) -> Array:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def row_parts(model: RobotModel, i: int) -> tuple[Array, Array]:
    """(A, B) of row ``i`` (mm): the row's transform is A · Rz(angle) · B."""
    j = model.joints[i]
    if model.convention == "dh":
        B = _rz(j.theta) @ _t(0, 0, j.d) @ _t(j.a, 0, 0) @ _rx(j.alpha) @ _ry(j.beta)
        return np.eye(4), B
    return _rx(j.alpha) @ _ry(j.beta) @ _t(j.a, 0, 0), _rz(j.theta) @ _t(0, 0, j.d)


def rpy(R: Array) -> tuple[float, float, float]:
    """URDF's roll, pitch, yaw: R = Rz(yaw) · Ry(pitch) · Rx(roll)."""
    pitch = math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2]))
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def _origin(T_mm: Array, what: str) -> ET.Element:
    """``<origin xyz rpy>`` (m, rad) of a transform, refused unless it reads back."""
    r, p, y = rpy(T_mm[:3, :3])
    back = (_rz(y) @ _ry(p) @ _rx(r))[:3, :3]
    if np.abs(back - T_mm[:3, :3]).max() > ROUND_TRIP:
        raise InputError(f"{what}: its rotation has no exact roll-pitch-yaw (pitch ±90°)")
    xyz = T_mm[:3, 3] / 1000.0
    return ET.Element(
        "origin",
        xyz=" ".join(repr(float(v)) for v in xyz),
        rpy=" ".join(repr(float(v)) for v in (r, p, y)),
    )


def _sign(model: RobotModel, i: int) -> float:
    j = model.joints[i]
    if j.couple_joint or j.scale not in (1.0, -1.0):
        raise InputError(
            f"joint {i + 1}: its angle is {j.scale:g} × its reading"
            + (f" + {j.couple_factor:g} × joint {j.couple_joint}'s" if j.couple_joint else "")
            + "; URDF joints turn by their own value (±1), so this model has no URDF form"
        )
    return j.scale


def _fixed(robot: ET.Element, name: str, parent: str, child: str, T: Array) -> None:
    joint = ET.SubElement(robot, "joint", name=name, type="fixed")
    joint.append(_origin(T, f"joint {name}"))
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    ET.SubElement(robot, "link", name=child)


def to_urdf(model: RobotModel, target_offset_mm: Array, T_sensor_base: Array | None = None) -> str:
    """The model as URDF text: ``base_link``, ``link_1..n`` turned by ``joint_1..n``,
    ``flange``, ``target`` at ``tool_mm`` on the flange, and for a calibrated model the
    ``sensor`` frame fixed to the base."""
    robot = ET.Element("robot", name=model.name)
    ET.SubElement(robot, "link", name="base_link")
    before = np.eye(4)  # B of the previous row
    parent = "base_link"
    lo, hi = model.limits
    for i in range(model.dof):
        A, B = row_parts(model, i)
        name, child = f"joint_{i + 1}", f"link_{i + 1}"
        bounded = math.isfinite(lo[i]) and math.isfinite(hi[i])
        joint = ET.SubElement(
            robot, "joint", name=name, type="revolute" if bounded else "continuous"
        )
        joint.append(_origin(before @ A, f"joint {i + 1}"))
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=child)
        ET.SubElement(joint, "axis", xyz=f"0 0 {_sign(model, i):g}")
        if bounded:
            ET.SubElement(
                joint,
                "limit",
                lower=repr(float(lo[i])),
                upper=repr(float(hi[i])),
                effort="0",
                velocity="0",
            )
        ET.SubElement(robot, "link", name=child)
        before, parent = B, child
    _fixed(robot, "flange_joint", parent, "flange", before)
    _fixed(
        robot, "target_joint", "flange", "target", _t(*np.asarray(target_offset_mm, dtype=float))
    )
    if T_sensor_base is not None:
        _fixed(robot, "sensor_joint", "base_link", "sensor", invert(np.asarray(T_sensor_base)))
    ET.indent(robot)
    comment = (
        f"<!-- {model.name}: written by cellcal from its {model.convention.upper()} model. "
        "Joint values are the controller's readings (rad); lengths m. effort and velocity "
        "are not part of a kinematic model: 0 here, give your own limits to a planner. -->\n"
    )
    return '<?xml version="1.0"?>\n' + comment + ET.tostring(robot, encoding="unicode") + "\n"


#: A foot point farther than this (mm) from its axis: the chain has no DH form.
ON_AXIS_MM = 1e-6
#: The imported model must reproduce the URDF's own positions this closely (mm).
AGREE_MM = 1e-6
#: ... and the end frame's axes this closely (largest difference of a matrix element).
AGREE_ROTATION = 1e-9
#: An end frame turned off the flange frame a DH model ends on by no more than this
#: (rad) is that flange frame (a file's rounded π/2 leaves 5e-12).
FLANGE_RAD = 1e-9
END_FRAMES = ("tool0", "flange")
#: A serial industrial arm has 6 or 7 joints, a redundant one with a track a few more.
MAX_DOF = 12


def _unit(v: Array) -> Array:
    out: Array = v / np.linalg.norm(v)
    return out


def _angle_about(u: Array, v: Array, axis: Array) -> float:
    return math.atan2(float(np.dot(np.cross(u, v), axis)), float(np.dot(u, v)))


def _rot(alpha: float, beta: float) -> Array:
    out: Array = (_rx(alpha) @ _ry(beta))[:3, :3]
    return out


def _twist(R: Array, z_next: Array) -> tuple[float, float]:
    """(α, β) with R · Rx(α) · Ry(β) · ez = ``z_next``."""
    u = R.T @ z_next
    return math.atan2(-u[1], u[2]), math.asin(max(-1.0, min(1.0, float(u[0]))))


def _frame(z: Array, x: Array) -> Array:
    return np.column_stack([x, np.cross(z, x), z])


def _next_frame(
    foot: Array, z_i: Array, x_twisted: Array, p_next: Array, z_next: Array
) -> tuple[Array, Array]:
    """Frame i's origin and x axis on axis i, chosen so that the next row reaches axis
    i + 1: the common normal of the two axes, or for axes within 1° of parallel
    (Hayati) the origin at ``foot`` and the x that, after the row's α and β, points
    square at axis i + 1."""
    c = np.cross(z_i, z_next)
    if np.linalg.norm(c) < math.sin(math.radians(PARALLEL_AXES_DEG)):
        w = p_next - foot
        w = w - np.dot(w, z_next) * z_next
        x2 = _unit(w) if np.linalg.norm(w) > ON_AXIS_MM else x_twisted
        R2 = _frame(z_next, _unit(x2 - np.dot(x2, z_next) * z_next))
        u = R2.T @ z_i  # = (Rx(α) Ry(β))ᵀ ez
        alpha = math.asin(max(-1.0, min(1.0, float(u[1]))))
        beta = math.atan2(-u[0], u[2])
        R_i = R2 @ _rot(alpha, beta).T
        return foot, R_i[:, 0]
    d = foot - p_next
    b = float(np.dot(z_i, z_next))
    f, g = float(np.dot(z_i, d)), float(np.dot(z_next, d))
    den = 1.0 - b * b
    foot_i = foot + ((b * g - f) / den) * z_i
    foot_next = p_next + ((g - b * f) / den) * z_next
    gap = foot_next - foot_i
    if np.linalg.norm(gap) < ON_AXIS_MM:  # intersecting axes
        return foot_i, _unit(c)
    return foot_i, _unit(gap)


def _swing(z_from: Array, z_to: Array, v: Array) -> Array:
    """``v`` turned by the least rotation that takes unit ``z_from`` to unit ``z_to``
    (about their common normal; at most 90° here)."""
    c = np.cross(z_from, z_to)
    s, cos = float(np.linalg.norm(c)), float(np.dot(z_from, z_to))
    if s == 0.0:
        return v
    k = c / s
    out: Array = v * cos + np.cross(k, v) * s + k * float(np.dot(k, v)) * (1.0 - cos)
    return out


def mdh_from_axes(
    points: Array,
    axes: Array,
    end: Array,
    limits: list[tuple[float, float]],
    name: str,
    end_axes: Array | None = None,
) -> RobotModel:
    """A modified-DH model from joint axes at the zero readings (points on them and unit
    directions, N×3, base frame, mm) and the end frame's origin (mm): rows by common
    normals (Hayati's β between axes within 1° of parallel), the end frame's origin as
    the ``[tool]`` offset.

    ``end_axes`` (3×3, columns x y z, base frame): the end frame's orientation at the
    zero readings. The last frame (the model's flange frame) is then that frame turned
    the least that puts its z on the last joint's axis, its origin the end frame's
    origin's foot on that axis: the end frame itself when its z is along the axis and
    its origin on it. A z against the axis makes the last joint's scale −1 (its frame's
    z is the file's axis reversed; the joint still turns by its reading about the
    file's axis). Without ``end_axes``, the last frame's x is that of the row's twist."""
    n = len(axes)
    z = [_unit(np.asarray(v, dtype=np.float64)) for v in axes]
    p = [np.asarray(v, dtype=np.float64) for v in points]
    last_scale = 1.0
    if end_axes is not None and float(np.dot(end_axes[:, 2], z[-1])) < 0.0:
        z[-1], last_scale = -z[-1], -1.0
    o, R = np.zeros(3), np.eye(3)
    joints = []
    for i in range(n):
        alpha, beta = _twist(R, z[i])
        x_twisted = (R @ _rot(alpha, beta))[:, 0]
        a = float(np.dot(p[i] - o, x_twisted))
        foot = o + a * x_twisted
        off = (foot - p[i]) - np.dot(foot - p[i], z[i]) * z[i]
        if np.linalg.norm(off) > ON_AXIS_MM:
            raise InputError(
                f"joint {i + 1}'s axis is {np.linalg.norm(off):.3g} mm off the normal of the "
                "axis before it"
                + (" (the base frame's)" if i == 0 else "")
                + ": the chain has no DH form"
            )
        if i + 1 < n:
            o_i, x_i = _next_frame(foot, z[i], x_twisted, p[i + 1], z[i + 1])
        else:
            o_i, x_i = foot + np.dot(end - foot, z[i]) * z[i], x_twisted
            if end_axes is not None:
                x_end = _swing(_unit(end_axes[:, 2]), z[i], end_axes[:, 0])
                x_i = _unit(x_end - np.dot(x_end, z[i]) * z[i])
        lo, hi = limits[i]
        joints.append(
            Joint(
                a=a,
                alpha=alpha,
                d=float(np.dot(o_i - foot, z[i])),
                theta=_angle_about(x_twisted, x_i, z[i]),
                beta=beta,
                q_min=lo,
                q_max=hi,
                scale=last_scale if i == n - 1 else 1.0,
            )
        )
        o, R = o_i, _frame(z[i], x_i)
    target_offset = R.T @ (end - o)
    return RobotModel(
        name,
        "mdh",
        tuple(joints),
        (float(target_offset[0]), float(target_offset[1]), float(target_offset[2])),
    )


def _set(pin: Any, pm: Any, q: Array, joint: int, angle: float) -> None:
    jm = pm.joints[joint]
    if jm.nq == 1:
        q[jm.idx_q] = angle
    else:  # an unbounded revolute joint: (cos, sin)
        q[jm.idx_q], q[jm.idx_q + 1] = math.cos(angle), math.sin(angle)


def _limit(value: float, default: float) -> float:
    return float(value) if math.isfinite(value) and abs(value) < 1e9 else default


def _checked_limits(p: Path, name: str, lo: float, hi: float) -> tuple[float, float]:
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise FileFormatError(f"{p}: joint {name!r} has limits {lo:g}..{hi:g}: not lower ≤ upper")
    return _limit(lo, -math.inf), _limit(hi, math.inf)


def model_from_urdf(path: str | Path, *, warn: Warn | None = warn_on_stderr) -> RobotModel:
    """A robot model from a URDF file (see the module's notes); refused, one line, when
    the file is not a URDF (:func:`cellcal.files.urdf_input.screen`: no DTD or entity, its
    joints and links bounded), Pinocchio does not read it, the chain is not of at most
    :data:`MAX_DOF` revolute joints, or the result does not reproduce the file's own
    kinematics."""
    p = Path(path)
    text = read_text(p, "a URDF file", limit=MAX_BYTES)
    screen(text, p)
    try:
        with np.errstate(all="ignore"):  # overflow of huge numbers: refused below
            return _from_urdf(p, text, warn)
    except (ArithmeticError, ValueError, IndexError, RuntimeError, np.linalg.LinAlgError) as exc:
        # NaN or huge numbers that passed Pinocchio's parser, or a std::exception of its
        # kinematics: the derived geometry is not usable.
        raise FileFormatError(
            f"{p}: its geometry gives no usable model ({first_line(exc)}): origins, axes "
            "and limits must be finite numbers of a robot's size"
        ) from None


def _from_urdf(p: Path, text: str, warn: Warn | None) -> RobotModel:
    import pinocchio as pin

    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise FileFormatError(f"{p}: not XML ({exc})") from None
    if root.tag != "robot":
        raise FileFormatError(f"{p}: not a URDF (its root element is <{root.tag}>, not <robot>)")
    pm = pinocchio_model(pin, p, text)
    names = [f.name for f in pm.frames]
    end_name = next((f for f in END_FRAMES if f in names), None)
    fid = pm.getFrameId(end_name) if end_name is not None else None
    last = pm.frames[fid].parentJoint if fid is not None else pm.njoints - 1
    end_label = repr(end_name if end_name is not None else _child_link(root, pm.names[last]))
    chain: list[int] = []
    j = int(last)
    while j > 0:
        chain.append(j)
        j = int(pm.parents[j])
    chain.reverse()
    if not chain:
        raise InputError(f"{p}: no joint between the root and the end frame")
    if len(chain) > MAX_DOF:
        raise InputError(
            f"{p}: {len(chain)} joints between the root and the end frame: at most "
            f"{MAX_DOF} (a serial industrial arm)"
        )
    for j in chain:
        kind = pm.joints[j].shortname()
        if pm.joints[j].nv != 1 or not kind.startswith(("JointModelR", "JointModelRevolute")):
            raise InputError(
                f"{p}: joint {pm.names[j]!r} is {kind.removeprefix('JointModel')}; cellcal "
                "models serial chains of revolute joints"
            )
    try:
        d = pm.createData()
    except Exception as exc:  # bad_alloc and the like: one line, not a traceback
        raise FileFormatError(f"{p}: Pinocchio cannot model it ({first_line(exc)})") from None

    def placements(readings: Array) -> tuple[Array, Array]:
        """The end frame's origins (N×3, mm) and axes (N×3×3) by Pinocchio."""
        out, turn = [], []
        for row in readings:
            q = pin.neutral(pm)
            for joint, angle in zip(chain, row, strict=True):
                _set(pin, pm, q, joint, float(angle))
            pin.framesForwardKinematics(pm, d, q)
            place = d.oMf[fid] if fid is not None else d.oMi[last]
            out.append(np.array(place.translation) * 1000.0)
            turn.append(np.array(place.rotation))
        return np.array(out), np.array(turn)

    q0 = pin.neutral(pm)
    for joint in chain:
        _set(pin, pm, q0, joint, 0.0)
    pin.computeJointJacobians(pm, d, q0)
    pin.framesForwardKinematics(pm, d, q0)
    points, axes, limits = [], [], []
    for joint in chain:
        J = pin.getJointJacobian(pm, d, joint, pin.ReferenceFrame.WORLD)
        axes.append(np.array(J[3:, pm.joints[joint].idx_v]))
        points.append(np.array(d.oMi[joint].translation) * 1000.0)
        jm = pm.joints[joint]
        if jm.nq == 1:
            lo_j = float(pm.lowerPositionLimit[jm.idx_q])
            hi_j = float(pm.upperPositionLimit[jm.idx_q])
            limits.append(_checked_limits(p, pm.names[joint], lo_j, hi_j))
        else:
            limits.append((-math.inf, math.inf))
    ends, end_axes = placements(np.zeros((1, len(chain))))
    norms = np.linalg.norm(np.array(axes), axis=1)
    finite = all(np.isfinite(v).all() for v in (np.array(points), ends, end_axes))
    if not finite or not (np.abs(norms - 1.0) < 1e-6).all():
        raise FileFormatError(
            f"{p}: its joint origins or axes are not finite numbers of a robot's size (NaN, "
            "inf, a zero axis or lengths beyond reach)"
        )
    model = mdh_from_axes(
        np.array(points), np.array(axes), ends[0], limits, pm.name or p.stem, end_axes[0]
    )
    model = with_inertials(model, pm, d, chain)
    # The end frame in the model's flange frame: a turn (identity but for a frame a DH
    # table cannot end on) and an origin (model.target_offset: zero but for one off the last axis).
    k0 = target_kinematics(model, np.zeros((1, len(chain))), model.target_offset, jacobian=False)
    turn = k0.R_flange[0].T @ end_axes[0]
    # The model must be the file's robot: compare at random readings within the limits.
    rng = np.random.default_rng(0)
    lo = np.array([max(a, -math.pi) for a, _ in limits])
    hi = np.array([min(b, math.pi) for _, b in limits])
    q = rng.uniform(lo, hi, (50, len(chain)))
    k = target_kinematics(model, q, model.target_offset, jacobian=False)
    theirs, their_axes = placements(q)
    worst = float(np.abs(k.p - theirs).max())
    if worst > AGREE_MM:
        raise InputError(
            f"{p}: the DH model derived from it is {worst:.3g} mm off the file's own "
            "kinematics; its chain has no DH form cellcal can use"
        )
    worst = float(np.abs(k.R_flange @ turn - their_axes).max())
    if worst > AGREE_ROTATION:
        raise InputError(
            f"{p}: the DH model derived from it turns the end frame {worst:.3g} rad off "
            "the file's own kinematics; its chain has no DH form cellcal can use"
        )
    line = _flange_warning(p, end_label, model, turn)
    if line is not None and warn is not None:
        warn(line)
    return model


def _child_link(root: ET.Element, joint: str) -> str:
    """The child link of the joint named ``joint`` (its name if the file has none)."""
    for j in root.iter("joint"):
        child = j.find("child")
        if j.get("name") == joint and child is not None and child.get("link"):
            return str(child.get("link"))
    return joint


def _flange_warning(p: Path, end: str, model: RobotModel, turn: Array) -> str | None:
    """One line when the file's end frame is not the model's flange frame: turned off it
    (``turn``: the end frame's axes in the flange frame) or its origin off the last
    joint's axis (``model.target_offset``); None when it is the flange frame."""
    w = so3_log(turn)
    angle = float(np.linalg.norm(w))
    off = float(np.linalg.norm(model.target_offset))
    if angle <= FLANGE_RAD and off <= ON_AXIS_MM:
        return None
    n = model.dof
    what = []
    if angle > FLANGE_RAD:
        axis = ", ".join(f"{round(float(v), 4) + 0.0:g}" for v in w / angle)
        what.append(f"is turned {math.degrees(angle):.6g}° about ({axis})")
    if off > ON_AXIS_MM:
        what.append(f"has its origin {off:.6g} mm off joint {n}'s axis")
    t = ", ".join(f"{round(float(v), 6) + 0.0:g}" for v in model.target_offset)
    return (
        f"{p}: its end frame {end} {' and '.join(what)}, relative to the flange frame "
        f"a DH model ends on (z along joint {n}'s axis, origin on it); cellcal's model "
        f"cannot carry that, so target_offset_mm and [tool] are in that flange frame, not "
        f"in {end}: a point at t in {end} is at ({t}) mm + R·t there, R that turn"
    )
