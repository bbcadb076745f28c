"""A protocol-level simulator of a Universal Robots controller that the unmodified
ur_rtde library (``rtde_control``, ``rtde_receive``) connects to and drives.

What it serves, on one host address (``127.0.0.x``; ur_rtde fixes the ports):

* RTDE on TCP 30004, protocol v2 (and v1): ``V``, ``v``, ``O``, ``I``, ``S``, ``P``, ``U``,
  big-endian. Output fields are packed with the types of ur_rtde's own unpacking table
  (it ignores the announced types); unknown names get ``NOT_FOUND``. Input recipes are
  numbered 1, 2, 3, ... per connection, as ur_rtde hard-codes the ids; an input name
  owned by another open connection gets ``IN_USE``.
* The dashboard server on 29999 (one line per request, ``\\n``-terminated).
* The script port 30003: a program ``def rtde_control(): ... end`` starts ur_rtde's
  control loop (runtime_state PLAYING); the loop is simulated, not interpreted.

The control loop follows ur_rtde's ``rtde_control.script``: ``output_int_register_0`` is 1
when ready and 2 when done with a command; the command is ``input_int_register_0`` (1
moveJ, 2 moveJ_IK, 3 moveL, 4 moveL_FK, 31 protective stop, 33 stopL, 34 stopJ, 255 stop
script) with values in ``input_double_register_0..7`` and ``async`` in
``input_int_register_1``; a clear (0) makes it ready again. Asynchronous moves report in
``output_int_register_2`` with the script's bit layout (running bit 15, progress bits
0-14, change counter bits 16-22, operation id bits 24-30).

Why a child process: pybind11 holds the GIL in ur_rtde's constructors
(``RTDEReceiveInterface(host)``, ``RTDEControlInterface(host)``), which block until the
controller has answered (first data package, script running). A server made of Python
threads in the same interpreter cannot answer then, and the constructor never returns.
So :class:`URSimulator` runs the wire protocol and the controller state machine in a
child process (stdlib only, one selector loop), and keeps the kinematics and the
``on_move`` hook in the calling process. They talk over the child's stdin/stdout in JSON
lines: the child reports each new joint position, the parent answers with the TCP pose
(``fk``) after calling ``on_move``; the child asks for ``ik`` when a move needs it. The
data packages carry the last acknowledged joint position with its pose (so actual_q and
actual_TCP_pose always agree, at the cost of a cycle of lag), and a synchronous move is
reported done only after a package with the final position has gone out, so ``on_move``
has seen it before ``moveJ`` returns.

Simplifications (the simulator is a test double of the protocol, not of the robot):

* Motion is a trapezoidal profile of the leading joint (moveJ) or of the TCP translation
  (moveL), interpolated linearly in joint space; a moveL reaches the target pose but its
  path is not a straight line. moveL_FK is timed like moveJ.
* A protective (or emergency) stop halts the robot and aborts the move in progress; the
  control script stays PLAYING but processes no command until the stop is cleared
  (``clear_protective_stop()`` or dashboard ``unlock protective stop``). A real
  controller pauses the program instead.
* An unreachable pose (``ik`` returns None) ends the control script, as the runtime
  error of ``get_inverse_kin`` does on a real controller: runtime_state goes to STOPPED.
* Commands other than the ones above are acknowledged without effect (logged).
* ``time_scale`` is wall seconds per simulated second; 0 makes every move finish in three
  RTDE cycles. Data packages go out at ``period_s`` (8 ms, 125 Hz) whatever frequency the
  client asked for.

Size (about 1600 lines, one class of about 800): not split yet. Issue 10's remaining
part splits the twins by job (links, protocol codecs, controller state, dashboard,
script port, a reusable TCP link server) together with the RTDE fidelity work (output
frequency, v1 framing, the 5.11 output fields), which rewrites the codec and the
controller loop; splitting before that would move the same lines twice. Mock mode
already drives it with cellcal's nominal model (``serve``); ``DHKinematics.ur10e`` is
left only for its own tests and goes with the split. Its tests
(``tests/mocks/test_ur_server.py``, driven by the unmodified ur_rtde) guard that split.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from cellcal.mocks.twins import UR_HOSTS, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.ur import UROptions
    from cellcal.mocks.simulated_cell import SimulatedCell
from numpy.typing import NDArray

log = logging.getLogger("cellcal.mocks.ur")

Vec = NDArray[np.float64]

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

CONTROLLER_VERSION = (5, 11, 1, 108318)
POLYSCOPE_VERSION = "URSoftware 5.11.1.108318 (Mar 22 2021)"
WELCOME = "Connected: Universal Robots Dashboard Server"
DEFAULT_SERIAL = "20215500001"
ROBOT_MODEL = "UR10"

#: A usual UR "home" (rad): arm up and elbow bent, wrist down.
HOME_Q = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)

# RTDE message types
_V, _CV, _M, _U, _O, _I, _S, _P = 86, 118, 77, 85, 79, 73, 83, 80
_HEADER = struct.Struct(">HB")

# Runtime states, robot modes, safety modes and bits (UR's and ur_rtde's numbering)
STOPPED, PLAYING, PAUSED = 1, 2, 4
_RUNTIME_NAMES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED"}
POWER_OFF, IDLE, RUNNING = 3, 5, 7
_ROBOT_MODE_NAMES = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 7: "RUNNING"}
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
_SAFETY_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}
BIT_NORMAL_MODE = 0
BIT_PROTECTIVE_STOPPED = 2
BIT_ROBOT_EMERGENCY_STOPPED = 6
BIT_EMERGENCY_STOPPED = 7
BIT_STOPPED_DUE_TO_SAFETY = 10
JOINT_RUNNING_MODE = 253

# Control-script protocol (rtde_control.script)
READY, DONE = 1, 2
CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_MOVEL_FK = 1, 2, 3, 4
CMD_PROTECTIVE_STOP, CMD_STOPL, CMD_STOPJ, CMD_STOP_SCRIPT = 31, 33, 34, 255

# ---------------------------------------------------------------------------------------
# Kinematics (calling process)
# ---------------------------------------------------------------------------------------


class URKinematics(Protocol):
    """Where the simulated robot's TCP is, and how to get there (SI units, base frame)."""

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Joint positions (rad, 6) → TCP pose [x, y, z, rx, ry, rz] (m, rotation vector)."""
        ...

    def ik(self, pose: np.ndarray, q_seed: np.ndarray) -> np.ndarray | None:
        """A joint solution near ``q_seed`` for ``pose``, or None if unreachable."""
        ...


class CellInURUnits:
    """The simulated cell's controller kinematics (brand-neutral: T_base_flange, 4×4 mm)
    in UR's units: [x, y, z] m and a rotation vector (rad)."""

    def __init__(self, cell: SimulatedCell) -> None:
        self.cell = cell

    def fk(self, q: np.ndarray) -> np.ndarray:
        T = self.cell.flange_pose(q)
        return np.concatenate([T[:3, 3] / 1000.0, matrix_to_rotvec(T[:3, :3])])

    def ik(self, pose: np.ndarray, q_seed: np.ndarray) -> np.ndarray | None:
        T = np.eye(4)
        T[:3, :3] = rotvec_to_matrix(np.asarray(pose[3:6], dtype=np.float64))
        T[:3, 3] = np.asarray(pose[:3], dtype=np.float64) * 1000.0
        return self.cell.joints_for(T, q_seed)


def _skew(w: Vec) -> Vec:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rotvec_to_matrix(w: np.ndarray) -> Vec:
    """Rotation matrix of a rotation vector (axis × angle, rad)."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    K = _skew(w)
    if theta < 1e-9:
        small: Vec = np.eye(3) + K + 0.5 * (K @ K)
        return small
    out: Vec = (
        np.eye(3) + (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta**2) * (K @ K)
    )
    return out


def matrix_to_rotvec(R: np.ndarray) -> Vec:
    """Rotation vector (rad) of a rotation matrix; stable near 0 and near π."""
    R = np.asarray(R, dtype=np.float64)
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(v))  # sin θ
    c = 0.5 * (float(np.trace(R)) - 1.0)  # cos θ
    theta = math.atan2(s, c)
    if theta < 1e-9:
        small: Vec = v.copy()
        return small
    if theta < math.pi / 2:
        out: Vec = (theta / s) * v
        return out
    # Near π: the axis from the symmetric part, S = c I + (1 - c) a aᵀ, sign from v.
    S = 0.5 * (R + R.T)
    k = int(np.argmax(np.diag(S)))
    ak = math.sqrt(max((S[k, k] - c) / (1.0 - c), 0.0))
    axis = S[:, k] / ((1.0 - c) * ak)
    axis[k] = ak
    axis /= np.linalg.norm(axis)
    along = float(axis @ v)
    if abs(along) < 1e-12:  # θ = π: ±axis are the same rotation; pick one for repeatability
        along = float(axis[int(np.argmax(np.abs(axis) > 1e-9))])
    if along < 0.0:
        axis = -axis
    res: Vec = theta * axis
    return res


class DHKinematics:
    """Standard DH (θᵢ = qᵢ; Rz(θ) Tz(d) Tx(a) Rx(α)) forward kinematics of a 6R arm and a
    small numeric inverse (damped least squares from the seed, a few restarts).

    Lengths are given in mm (as everywhere in cellcal) and used in m, as URScript does."""

    def __init__(self, a_mm: np.ndarray, d_mm: np.ndarray, alpha_deg: np.ndarray) -> None:
        self.a = np.asarray(a_mm, dtype=np.float64) / 1000.0
        self.d = np.asarray(d_mm, dtype=np.float64) / 1000.0
        self.alpha = np.radians(np.asarray(alpha_deg, dtype=np.float64))
        if not (self.a.shape == self.d.shape == self.alpha.shape == (6,)):
            raise ValueError("DH tables must have 6 rows")

    @classmethod
    def ur10e(cls) -> DHKinematics:
        return cls(
            a_mm=np.array([0.0, -612.7, -571.55, 0.0, 0.0, 0.0]),
            d_mm=np.array([180.7, 0.0, 0.0, 174.15, 119.85, 116.55]),
            alpha_deg=np.array([90.0, 0.0, 0.0, 90.0, -90.0, 0.0]),
        )

    def frames(self, q: np.ndarray) -> list[Vec]:
        """T_base_i for i = 0..6 (T_base_0 = I), in m."""
        q = np.asarray(q, dtype=np.float64)
        T = np.eye(4)
        out = [T]
        for i in range(6):
            ct, st = math.cos(q[i]), math.sin(q[i])
            ca, sa = math.cos(self.alpha[i]), math.sin(self.alpha[i])
            A = np.array(
                [
                    [ct, -st * ca, st * sa, self.a[i] * ct],
                    [st, ct * ca, -ct * sa, self.a[i] * st],
                    [0.0, sa, ca, self.d[i]],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            )
            T = T @ A
            out.append(T)
        return out

    def fk(self, q: np.ndarray) -> np.ndarray:
        T = self.frames(q)[-1]
        return np.concatenate([T[:3, 3], matrix_to_rotvec(T[:3, :3])])

    def _error_and_jacobian(self, q: Vec, p_t: Vec, R_t: Vec) -> tuple[Vec, Vec]:
        Ts = self.frames(q)
        p_e = Ts[-1][:3, 3]
        J = np.empty((6, 6))
        for i in range(6):
            z = Ts[i][:3, 2]
            J[:3, i] = np.cross(z, p_e - Ts[i][:3, 3])
            J[3:, i] = z
        e = np.concatenate([p_t - p_e, matrix_to_rotvec(R_t @ Ts[-1][:3, :3].T)])
        return e, J

    def ik(
        self, pose: np.ndarray, q_seed: np.ndarray, *, tol: float = 1e-10, max_iter: int = 100
    ) -> np.ndarray | None:
        pose = np.asarray(pose, dtype=np.float64)
        q_seed = np.asarray(q_seed, dtype=np.float64)
        if pose.shape != (6,) or q_seed.shape != (6,) or not np.all(np.isfinite(pose)):
            return None
        p_t, R_t = pose[:3], rotvec_to_matrix(pose[3:])
        rng = np.random.default_rng(0)
        starts = [q_seed] + [q_seed + rng.uniform(-0.5, 0.5, 6) for _ in range(4)]
        for q0 in starts:
            q = q0.copy()
            for _ in range(max_iter):
                e, J = self._error_and_jacobian(q, p_t, R_t)
                err = float(np.linalg.norm(e))
                if err < tol:
                    return q
                lam2 = 1e-6 + 1e-2 * err * err
                dq = J.T @ np.linalg.solve(J @ J.T + lam2 * np.eye(6), e)
                n = float(np.linalg.norm(dq))
                if n > 0.5:
                    dq *= 0.5 / n
                q = q + dq
            e, _ = self._error_and_jacobian(q, p_t, R_t)
            if float(np.linalg.norm(e)) < 1e-8:
                return q
        return None


# ---------------------------------------------------------------------------------------
# The simulator as seen from the calling process
# ---------------------------------------------------------------------------------------


class URSimulator:
    """A simulated UR controller on ``host``:30004/29999/30003 (see the module docstring).

    ``on_move(q)`` is called from the simulator's reader thread each time the joints
    change (at most once per RTDE cycle; always with the final position of a move)."""

    def __init__(
        self,
        kinematics: URKinematics,
        *,
        q0: np.ndarray,
        time_scale: float = 0.0,
        on_move: Callable[[np.ndarray], None] | None = None,
        period_s: float = 0.008,
        serial_number: str = DEFAULT_SERIAL,
        start_timeout_s: float = 15.0,
    ) -> None:
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape != (6,) or not np.all(np.isfinite(q0)):
            raise ValueError("q0 must be 6 finite joint positions (rad)")
        if not (math.isfinite(time_scale) and time_scale >= 0.0):
            raise ValueError("time_scale must be >= 0")
        if not (0.001 <= period_s <= 0.1):
            raise ValueError("period_s must be within 1 ms .. 100 ms")
        if not serial_number.isdigit():
            raise ValueError("serial_number must be digits (ur_rtde checks it is a number)")
        self.kinematics = kinematics
        self.time_scale = float(time_scale)
        self.on_move = on_move
        self.period_s = float(period_s)
        self.serial_number = serial_number
        self.start_timeout_s = start_timeout_s
        self._q = q0.copy()
        self._pose = np.zeros(6)
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        self._listening = threading.Event()
        self._is_listening = False
        self._start_error: str | None = None
        self._replies: dict[int, threading.Event] = {}
        self._next_id = 1
        self.host: str | None = None

    # -- public -------------------------------------------------------------------------

    @property
    def q(self) -> np.ndarray:
        """The joint positions (rad) last reported by the controller."""
        with self._lock:
            return self._q.copy()

    @property
    def tcp_pose(self) -> np.ndarray:
        """The TCP pose [m, rad rotation vector] last computed for :attr:`q`."""
        with self._lock:
            return self._pose.copy()

    def start(self, host: str) -> None:
        """Bind host:30004, :29999 and :30003; return once all three listen."""
        if self._proc is not None:
            raise RuntimeError("simulator already started")
        pose0 = np.asarray(self.kinematics.fk(self._q), dtype=np.float64)
        self._pose = pose0
        cfg = {
            "host": host,
            "q0": self._q.tolist(),
            "pose0": pose0.tolist(),
            "time_scale": self.time_scale,
            "period_s": self.period_s,
            "serial": self.serial_number,
            "log_level": logging.getLogger("cellcal").getEffectiveLevel(),
        }
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        code = "import sys; from cellcal.mocks.ur_server import _child_main; "
        code += "sys.exit(_child_main(sys.argv[1]))"
        self._listening.clear()
        self._is_listening = False
        self._start_error = None
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code, json.dumps(cfg)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self.host = host
        self._reader = threading.Thread(target=self._read_child, name=f"ur-sim-{host}", daemon=True)
        self._reader.start()
        self._listening.wait(self.start_timeout_s)
        if not self._is_listening:
            err = self._start_error or f"not listening within {self.start_timeout_s:g} s"
            self.stop()
            raise OSError(f"UR simulator on {host}: {err}")

    def stop(self) -> None:
        """Close every port and end the child process (idempotent)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            self._send_raw(proc, {"t": "quit"})
        with contextlib.suppress(OSError, ValueError):
            if proc.stdin is not None:
                proc.stdin.close()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5.0)
        if self._reader is not None:
            self._reader.join(timeout=5.0)
            self._reader = None
        if proc.stdout is not None:
            proc.stdout.close()

    def inject_protective_stop(self) -> None:
        """Protective stop: safety_status_bits bit 2, the robot halts, a move fails.

        This and the other safety calls return two RTDE cycles after the new state was
        sent, so that connected clients have it."""
        self._request({"t": "safety", "what": "protective", "on": True})

    def clear_protective_stop(self) -> None:
        """As dashboard ``unlock protective stop``."""
        self._request({"t": "safety", "what": "protective", "on": False})

    def inject_emergency_stop(self) -> None:
        """Robot emergency stop: safety_status_bits bits 6 and 7, the robot halts."""
        self._request({"t": "safety", "what": "emergency", "on": True})

    def clear_emergency_stop(self) -> None:
        self._request({"t": "safety", "what": "emergency", "on": False})

    def __enter__(self) -> URSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- child link -------------------------------------------------------------------

    def _send_raw(self, proc: subprocess.Popen[bytes], msg: dict[str, Any]) -> None:
        data = (json.dumps(msg) + "\n").encode()
        with self._write_lock:
            assert proc.stdin is not None
            proc.stdin.write(data)
            proc.stdin.flush()

    def _send(self, msg: dict[str, Any]) -> None:
        proc = self._proc
        if proc is None:
            return
        try:
            self._send_raw(proc, msg)
        except (OSError, ValueError) as e:
            log.warning("UR simulator %s: cannot reach the child process: %s", self.host, e)

    def _request(self, msg: dict[str, Any], timeout: float = 5.0) -> None:
        if self._proc is None:
            raise RuntimeError("simulator not started")
        with self._lock:
            rid = self._next_id
            self._next_id += 1
            ev = threading.Event()
            self._replies[rid] = ev
        self._send({**msg, "id": rid})
        ok = ev.wait(timeout)
        with self._lock:
            self._replies.pop(rid, None)
        if not ok:
            raise RuntimeError(f"UR simulator {self.host}: no answer to {msg['t']}")

    def _read_child(self) -> None:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        for raw in proc.stdout:
            try:
                msg = json.loads(raw)
            except ValueError:
                log.warning("UR simulator %s: bad line from child: %r", self.host, raw[:200])
                continue
            t = msg.get("t")
            if t == "q":
                self._on_q(int(msg["seq"]), np.asarray(msg["q"], dtype=np.float64))
            elif t == "ik":
                self._on_ik(int(msg["id"]), msg["pose"], msg["seed"])
            elif t == "ok":
                with self._lock:
                    ev = self._replies.get(int(msg["id"]))
                if ev is not None:
                    ev.set()
            elif t == "listening":
                self._is_listening = True
                self._listening.set()
            elif t == "error":
                self._start_error = str(msg.get("msg"))
                self._listening.set()
        if not self._is_listening and self._start_error is None:
            self._start_error = "the simulator process ended before listening"
        self._listening.set()

    def _on_q(self, seq: int, q: Vec) -> None:
        try:
            pose = np.asarray(self.kinematics.fk(q), dtype=np.float64)
            if pose.shape != (6,) or not np.all(np.isfinite(pose)):
                raise ValueError(f"fk returned {pose!r}")
        except Exception:
            log.exception("UR simulator %s: fk failed; the TCP pose is stale", self.host)
            pose = self.tcp_pose
        with self._lock:
            self._q = q.copy()
            self._pose = pose
        if self.on_move is not None:
            try:
                self.on_move(q.copy())
            except Exception:
                log.exception("UR simulator %s: on_move failed", self.host)
        self._send({"t": "pose", "seq": seq, "pose": pose.tolist()})

    def _on_ik(self, rid: int, pose: list[float], seed: list[float]) -> None:
        q: np.ndarray | None
        try:
            q = self.kinematics.ik(np.asarray(pose, float), np.asarray(seed, float))
            if q is not None:
                q = np.asarray(q, dtype=np.float64)
                if q.shape != (6,) or not np.all(np.isfinite(q)):
                    q = None
        except Exception:
            log.exception("UR simulator %s: ik failed", self.host)
            q = None
        self._send({"t": "ikr", "id": rid, "q": None if q is None else q.tolist()})


def serve(options: UROptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of a configured UR controller: the first free loopback address of its
    range (the ports are fixed), the simulated cell's nominal kinematics in UR's units."""
    from cellcal.errors import DeviceError

    last: Exception | None = None
    for host in UR_HOSTS:
        sim = URSimulator(
            CellInURUnits(cell),
            q0=np.radians(options.home_deg),
            time_scale=time_scale,
            on_move=cell.set_q,
        )
        try:
            sim.start(host)
        except OSError as exc:  # another simulated UR holds this address's fixed ports
            last = exc
            continue
        return RunningTwin(options.model_copy(update={"address": host}), sim)
    raise DeviceError(f"no free loopback address for a simulated UR ({last})")


# ---------------------------------------------------------------------------------------
# Child process: wire protocol and controller state (stdlib only)
# ---------------------------------------------------------------------------------------

_CODES = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

_D, _V3, _V6, _U32, _I32, _U64, _V6I = (
    "DOUBLE",
    "VECTOR3D",
    "VECTOR6D",
    "UINT32",
    "INT32",
    "UINT64",
    "VECTOR6INT32",
)

#: Output types as ur_rtde unpacks them (robot_state.cpp; 3-vectors per rtde.cpp), and
#: a few more outputs of the RTDE guide that ur_rtde does not know.
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": _D,
    "target_q": _V6,
    "target_qd": _V6,
    "target_qdd": _V6,
    "target_current": _V6,
    "target_moment": _V6,
    "actual_q": _V6,
    "actual_qd": _V6,
    "actual_qdd": _V6,
    "actual_current": _V6,
    "actual_moment": _V6,
    "joint_control_output": _V6,
    "actual_TCP_pose": _V6,
    "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6,
    "target_TCP_pose": _V6,
    "target_TCP_speed": _V6,
    "actual_digital_input_bits": _U64,
    "joint_temperatures": _V6,
    "actual_execution_time": _D,
    "robot_mode": _I32,
    "joint_mode": _V6I,
    "safety_mode": _I32,
    "safety_status": _I32,
    "actual_tool_accelerometer": _V3,
    "speed_scaling": _D,
    "target_speed_fraction": _D,
    "actual_momentum": _D,
    "actual_main_voltage": _D,
    "actual_robot_voltage": _D,
    "actual_robot_current": _D,
    "actual_joint_voltage": _V6,
    "actual_digital_output_bits": _U64,
    "runtime_state": _U32,
    "robot_status_bits": _U32,
    "safety_status_bits": _U32,
    "standard_analog_input0": _D,
    "standard_analog_input1": _D,
    "standard_analog_output0": _D,
    "standard_analog_output1": _D,
    "analog_io_types": _U32,
    "io_current": _D,
    "euromap67_input_bits": _U32,
    "euromap67_output_bits": _U32,
    "tool_mode": _U32,
    "tool_analog_input_types": _U32,
    "tool_analog_input0": _D,
    "tool_analog_input1": _D,
    "tool_output_voltage": _I32,
    "tool_output_current": _D,
    "tool_temperature": _D,
    "tcp_force_scalar": _D,
    "elbow_position": _V3,
    "elbow_velocity": _V3,
    "script_control_line": _U32,
    "ft_raw_wrench": _V6,
    "payload": _D,
    "payload_cog": _V3,
    "payload_inertia": _V6,
    "output_bit_registers0_to_31": _U32,
    "output_bit_registers32_to_63": _U32,
    "input_bit_registers0_to_31": _U32,
    "input_bit_registers32_to_63": _U32,
}
for _i in range(48):
    OUTPUT_TYPES[f"output_int_register_{_i}"] = _I32
    OUTPUT_TYPES[f"output_double_register_{_i}"] = _D
    OUTPUT_TYPES[f"input_int_register_{_i}"] = _I32
    OUTPUT_TYPES[f"input_double_register_{_i}"] = _D
for _i in range(64, 128):
    OUTPUT_TYPES[f"output_bit_register_{_i}"] = "BOOL"
    OUTPUT_TYPES[f"input_bit_register_{_i}"] = "BOOL"

INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": _U32,
    "speed_slider_fraction": _D,
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": _D,
    "standard_analog_output_1": _D,
    "input_bit_registers0_to_31": _U32,
    "input_bit_registers32_to_63": _U32,
    "external_force_torque": _V6,
}
for _i in range(48):
    INPUT_TYPES[f"input_int_register_{_i}"] = _I32
    INPUT_TYPES[f"input_double_register_{_i}"] = _D
for _i in range(64, 128):
    INPUT_TYPES[f"input_bit_register_{_i}"] = "BOOL"

_REG = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)")


@dataclass
class _Motion:
    """q(t) = q0 + (q1 - q0)·s(t)/D, s a trapezoidal profile (distance D, v, a)."""

    q0: list[float]
    q1: list[float]
    dist: float
    v: float
    a: float
    is_async: bool
    t: float = 0.0
    t_acc: float = field(init=False)
    v_peak: float = field(init=False)
    duration: float = field(init=False)

    def __post_init__(self) -> None:
        self.v = max(self.v, 1e-3)
        self.a = max(self.a, 1e-3)
        D, v, a = self.dist, self.v, self.a
        if D <= 0.0:
            self.t_acc, self.v_peak, self.duration = 0.0, 0.0, 0.0
        elif v * v / a >= D:  # triangular
            self.t_acc = math.sqrt(D / a)
            self.v_peak = a * self.t_acc
            self.duration = 2.0 * self.t_acc
        else:
            self.t_acc = v / a
            self.v_peak = v
            self.duration = 2.0 * self.t_acc + (D - v * self.t_acc) / v

    def sample(self) -> tuple[list[float], list[float]]:
        """Position and velocity at the current time."""
        t, T, ta, a, vp, D = self.t, self.duration, self.t_acc, self.a, self.v_peak, self.dist
        if D <= 0.0 or t >= T:
            return list(self.q1), [0.0] * 6
        if t < ta:
            s, sd = 0.5 * a * t * t, a * t
        elif t <= T - ta:
            s, sd = 0.5 * a * ta * ta + vp * (t - ta), vp
        else:
            r = T - t
            s, sd = D - 0.5 * a * r * r, a * r
        f, fd = s / D, sd / D
        q = [x0 + (x1 - x0) * f for x0, x1 in zip(self.q0, self.q1, strict=True)]
        qd = [(x1 - x0) * fd for x0, x1 in zip(self.q0, self.q1, strict=True)]
        return q, qd


@dataclass
class _Pending:
    """A synchronous command the control loop is executing."""

    kind: str  # "move" (waiting for arrival) or "ik" (waiting for the parent)
    cmd: int
    ik_id: int = 0
    v: float = 0.0
    a: float = 0.0
    is_async: bool = False
    pose: list[float] = field(default_factory=list)


class _Conn:
    def __init__(self, kind: str, sock: socket.socket, cid: int) -> None:
        self.kind = kind
        self.sock = sock
        self.cid = cid
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.closed = False
        # RTDE
        self.protocol = 1
        self.started = False
        self.outputs: list[tuple[int, struct.Struct, list[Callable[[], Any]]]] = []
        self.inputs: dict[int, tuple[struct.Struct, list[tuple[str, str]]]] = {}
        # script
        self.program: list[str] | None = None
        self.program_name = ""


def _flatten(values: list[Any]) -> list[Any]:
    out: list[Any] = []
    for v in values:
        if isinstance(v, list | tuple):
            out.extend(v)
        else:
            out.append(v)
    return out


class _Controller:
    """The simulated controller: state, control loop, wire protocols (child process)."""

    def __init__(self, cfg: dict[str, Any], out_fd: int) -> None:
        self.host: str = cfg["host"]
        self.time_scale = float(cfg["time_scale"])
        self.period = float(cfg["period_s"])
        self.serial = str(cfg["serial"])
        self.q: list[float] = [float(x) for x in cfg["q0"]]  # where the joints are
        # What clients are told: the last position the parent acknowledged, with its pose.
        self.q_pub = list(self.q)
        self.q_sent = list(self.q)
        self.qd = [0.0] * 6
        self.tcp: list[float] = [float(x) for x in cfg["pose0"]]
        self.sim_time = 0.0
        self.runtime_state = STOPPED
        self.robot_mode = RUNNING
        self.protective = False
        self.emergency = False
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.in_bits = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.out_bits = 0
        self.inputs_misc: dict[str, Any] = {}
        self.input_owner: dict[str, int] = {}
        self.motion: _Motion | None = None
        self.program_name = ""
        self.control_loaded = False
        self.executing = False
        self.pending: _Pending | None = None
        self.async_op_id = 0
        self.async_wr_count = 0
        self.async_finish_pending = False
        self.q_seq = 0
        self.q_acked = 0
        self.q_dirty = False
        self.ik_next = 1
        self.pending_oks: list[list[int]] = []
        self.settled_sent = True
        self.running = True
        self.sel = selectors.DefaultSelector()
        self.conns: dict[int, _Conn] = {}
        self.next_cid = 1
        self.out_fd = out_fd
        self.parent_out = bytearray()
        self.parent_in = bytearray()
        self.parent_writing = False
        self.last_tick = time.monotonic()

    # -- parent link --------------------------------------------------------------------

    def to_parent(self, msg: dict[str, Any]) -> None:
        self.parent_out += (json.dumps(msg) + "\n").encode()
        self._flush_parent()

    def _flush_parent(self) -> None:
        while self.parent_out:
            try:
                n = os.write(self.out_fd, self.parent_out)
            except BlockingIOError:
                break
            except OSError:
                self.running = False
                self.parent_out.clear()
                return
            del self.parent_out[:n]
        want = bool(self.parent_out)
        if want != self.parent_writing:
            self.parent_writing = want
            if want:
                self.sel.register(self.out_fd, selectors.EVENT_WRITE, ("parent_out", None))
            else:
                self.sel.unregister(self.out_fd)

    def _read_parent(self) -> None:
        try:
            data = os.read(0, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self.running = False
            return
        self.parent_in += data
        while b"\n" in self.parent_in:
            line, _, rest = self.parent_in.partition(b"\n")
            self.parent_in = bytearray(rest)
            if line.strip():
                self._on_parent(json.loads(line))

    def _on_parent(self, msg: dict[str, Any]) -> None:
        t = msg.get("t")
        if t == "pose":
            seq = int(msg["seq"])
            if seq == self.q_seq:
                self.q_acked = seq
                self.q_pub = self.q_sent
                self.tcp = [float(x) for x in msg["pose"]]
                self.settled_sent = False
            self._sync_q()
        elif t == "ikr":
            self._on_ik_reply(int(msg["id"]), msg["q"])
        elif t == "safety":
            on = bool(msg["on"])
            if msg["what"] == "protective":
                self.set_protective(on)
            else:
                self.set_emergency(on)
            # Answer a few cycles after the new state went out, so that clients have it.
            self.pending_oks.append([int(msg["id"]), 3])
        elif t == "quit":
            self.running = False

    def _sync_q(self) -> None:
        if self.q_dirty and self.q_acked == self.q_seq:
            self.q_seq += 1
            self.q_dirty = False
            self.q_sent = list(self.q)
            self.to_parent({"t": "q", "seq": self.q_seq, "q": self.q_sent})

    @property
    def settled(self) -> bool:
        """The parent has seen the current joint position (on_move called, TCP pose
        known) and a data package with both has gone to every client. "Done" waits for
        this, so a client reading another connection after a move sees the end state."""
        return not self.q_dirty and self.q_acked == self.q_seq and self.settled_sent

    # -- motion and safety ------------------------------------------------------------

    def halt(self) -> None:
        if (self.motion is not None and self.motion.is_async) or self.async_finish_pending:
            self._write_async(-1)
        self.motion = None
        self.async_finish_pending = False
        self.qd = [0.0] * 6

    @property
    def safety_stopped(self) -> bool:
        return self.protective or self.emergency

    def set_protective(self, on: bool) -> None:
        if on and not self.protective:
            log.info("UR simulator %s: protective stop", self.host)
            self._safety_halt()
        self.protective = on

    def set_emergency(self, on: bool) -> None:
        if on and not self.emergency:
            log.info("UR simulator %s: emergency stop", self.host)
            self._safety_halt()
        self.emergency = on

    def _safety_halt(self) -> None:
        self.halt()
        # The command in progress is abandoned without "done": ur_rtde sees the safety
        # bits and returns False, then clears the command.
        self.pending = None

    def start_motion(
        self, q1: list[float], v: float, a: float, is_async: bool, cart_m: float | None
    ) -> None:
        """Move to ``q1``. Joint moves are timed on the leading joint (v rad/s, a rad/s²);
        linear moves (``cart_m``, the TCP translation) on the TCP (v m/s, a m/s²), or, for
        a pure reorientation, on the leading joint at 1.05 rad/s and 1.4 rad/s²."""
        dist = max(abs(x1 - x0) for x0, x1 in zip(self.q, q1, strict=True))
        if cart_m is not None and cart_m > 1e-9:
            m = _Motion(list(self.q), list(q1), cart_m, v, a, is_async)
        elif cart_m is not None:
            m = _Motion(list(self.q), list(q1), dist, 1.05, 1.4, is_async)
        else:
            m = _Motion(list(self.q), list(q1), dist, v, a, is_async)
        self.motion = m
        if is_async:
            self._write_async(0)

    def advance(self, dt: float) -> None:
        m = self.motion
        if m is None:
            return
        m.t += dt
        q, qd = m.sample()
        if q != self.q:
            self.q = q
            self.q_dirty = True
        self.qd = qd
        if m.t >= m.duration:
            self.motion = None
            self.qd = [0.0] * 6
            if m.is_async:
                self.async_finish_pending = True

    # -- control loop (rtde_control.script) ------------------------------------------

    def _write_async(self, value: int) -> None:
        self.async_wr_count += 1
        if self.async_wr_count > 127:
            self.async_wr_count = 0
        if value == 0:
            self.async_op_id += 1
            if self.async_op_id > 127:
                self.async_op_id = 0
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[2] = reg

    def load_program(self, name: str, text: str) -> None:
        if self.robot_mode != RUNNING or self.safety_stopped:
            log.warning(
                "UR simulator %s: program %r not started (robot mode %s, safety %s)",
                self.host,
                name,
                _ROBOT_MODE_NAMES.get(self.robot_mode, self.robot_mode),
                self.safety_name(),
            )
            return
        self.halt()
        self.program_name = name
        if name == "rtde_control":
            self._start_control_loop()
        else:
            log.info("UR simulator %s: program %r run (no effect simulated)", self.host, name)
            self.control_loaded = False
            self.runtime_state = STOPPED

    def _start_control_loop(self) -> None:
        self.control_loaded = True
        self.runtime_state = PLAYING
        self.executing = False
        self.pending = None
        self._write_async(-1)
        self.out_int[0] = READY

    def stop_program(self) -> None:
        self.halt()
        self.pending = None
        self.control_loaded = False
        self.runtime_state = STOPPED

    def control_step(self) -> None:
        if not self.control_loaded or self.runtime_state != PLAYING or self.safety_stopped:
            return
        if self.async_finish_pending and self.settled:
            self.async_finish_pending = False
            self._write_async(-1)
        p = self.pending
        if p is not None:
            if p.kind == "move" and self.motion is None and self.settled:
                self.pending = None
                self.out_int[0] = DONE
            return
        cmd = self.in_int[0]
        if cmd == 0:
            self.executing = False
            self.out_int[0] = READY
            return
        if self.executing:
            return
        self.executing = True
        self.process(cmd)

    def process(self, cmd: int) -> None:
        vals = self.in_double[:6]
        v, a = self.in_double[6], self.in_double[7]
        is_async = self.in_int[1] == 1
        if cmd in (CMD_MOVEJ, CMD_MOVEL_FK):
            self._stop_async_move()
            self.start_motion(vals, v, a, is_async, None)
            self._after_start(is_async)
        elif cmd in (CMD_MOVEJ_IK, CMD_MOVEL):
            rid = self.ik_next
            self.ik_next += 1
            self.pending = _Pending("ik", cmd, rid, v, a, is_async, list(vals))
            self.to_parent({"t": "ik", "id": rid, "pose": list(vals), "seed": list(self.q)})
        elif cmd in (CMD_STOPJ, CMD_STOPL):
            self.halt()
            self.out_int[0] = DONE
        elif cmd == CMD_PROTECTIVE_STOP:
            self.set_protective(True)
        elif cmd == CMD_STOP_SCRIPT:
            log.info("UR simulator %s: control script stopped by the client", self.host)
            self.stop_program()
        else:
            log.info("UR simulator %s: command %d acknowledged, not simulated", self.host, cmd)
            self.out_int[0] = DONE

    def _after_start(self, is_async: bool) -> None:
        if is_async:
            self.out_int[0] = DONE
        else:
            self.pending = _Pending("move", CMD_MOVEJ)

    def _stop_async_move(self) -> None:
        if self.motion is not None and self.motion.is_async:
            self.halt()

    def _on_ik_reply(self, rid: int, q: list[float] | None) -> None:
        p = self.pending
        if p is None or p.kind != "ik" or p.ik_id != rid:
            return  # abandoned (safety stop, script stopped)
        self.pending = None
        if q is None:
            log.warning(
                "UR simulator %s: no inverse kinematics for pose %s; the control script ends",
                self.host,
                [round(x, 6) for x in p.pose],
            )
            self.stop_program()
            return
        self._stop_async_move()
        if p.cmd == CMD_MOVEL:
            cart = math.dist(self.tcp[:3], p.pose[:3])
            self.start_motion([float(x) for x in q], p.v, p.a, p.is_async, cart)
        else:
            self.start_motion([float(x) for x in q], p.v, p.a, p.is_async, None)
        self._after_start(p.is_async)

    # -- values -----------------------------------------------------------------------

    def safety_bits(self) -> int:
        bits = 0
        if self.protective:
            bits |= (1 << BIT_PROTECTIVE_STOPPED) | (1 << BIT_STOPPED_DUE_TO_SAFETY)
        if self.emergency:
            bits |= (1 << BIT_ROBOT_EMERGENCY_STOPPED) | (1 << BIT_EMERGENCY_STOPPED)
            bits |= 1 << BIT_STOPPED_DUE_TO_SAFETY
        if not bits:
            bits = 1 << BIT_NORMAL_MODE
        return bits

    def safety_mode(self) -> int:
        if self.emergency:
            return SAFETY_ROBOT_EMERGENCY_STOP
        if self.protective:
            return SAFETY_PROTECTIVE_STOP
        return SAFETY_NORMAL

    def safety_name(self) -> str:
        return _SAFETY_NAMES[self.safety_mode()]

    def robot_status_bits(self) -> int:
        bits = 0
        if self.robot_mode != POWER_OFF:
            bits |= 1
        if self.runtime_state == PLAYING:
            bits |= 2
        return bits

    def output_getter(self, name: str) -> Callable[[], Any] | None:
        z6 = [0.0] * 6
        fixed: dict[str, Callable[[], Any]] = {
            "timestamp": lambda: self.sim_time,
            "target_q": lambda: self.q_pub,
            "actual_q": lambda: self.q_pub,
            "target_qd": lambda: self.qd,
            "actual_qd": lambda: self.qd,
            "actual_TCP_pose": lambda: self.tcp,
            "target_TCP_pose": lambda: self.tcp,
            "joint_temperatures": lambda: [30.0] * 6,
            "actual_execution_time": lambda: 0.1,
            "robot_mode": lambda: self.robot_mode,
            "joint_mode": lambda: [JOINT_RUNNING_MODE] * 6,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "actual_tool_accelerometer": lambda: [0.0, 0.0, -9.81],
            "speed_scaling": lambda: 1.0,
            "target_speed_fraction": lambda: 1.0,
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 48.0,
            "actual_robot_current": lambda: 0.5,
            "actual_joint_voltage": lambda: [48.0] * 6,
            "runtime_state": lambda: self.runtime_state,
            "robot_status_bits": self.robot_status_bits,
            "safety_status_bits": self.safety_bits,
            "tool_temperature": lambda: 30.0,
            "output_bit_registers0_to_31": lambda: self.out_bits & 0xFFFFFFFF,
            "output_bit_registers32_to_63": lambda: (self.out_bits >> 32) & 0xFFFFFFFF,
            "input_bit_registers0_to_31": lambda: self.in_bits & 0xFFFFFFFF,
            "input_bit_registers32_to_63": lambda: (self.in_bits >> 32) & 0xFFFFFFFF,
        }
        if name in fixed:
            return fixed[name]
        m = _REG.fullmatch(name)
        if m is not None:
            io, kind, idx = m.group(1), m.group(2), int(m.group(3))
            if kind == "int":
                arr_i = self.out_int if io == "output" else self.in_int
                return lambda: arr_i[idx]
            if kind == "double":
                arr_d = self.out_double if io == "output" else self.in_double
                return lambda: arr_d[idx]
            if io == "output":
                return lambda: bool((self.out_bits >> idx) & 1)
            return lambda: bool((self.in_bits >> idx) & 1)
        typ = OUTPUT_TYPES.get(name)
        if typ is None:
            return None
        if typ == _V6:
            return lambda: z6
        if typ == _V3:
            return lambda: [0.0, 0.0, 0.0]
        if typ == _V6I:
            return lambda: [0] * 6
        if typ == _D:
            return lambda: 0.0
        if typ == "BOOL":
            return lambda: False
        return lambda: 0

    def set_input(self, name: str, value: Any) -> None:
        m = _REG.fullmatch(name)
        if m is not None and m.group(1) == "input":
            kind, idx = m.group(2), int(m.group(3))
            if kind == "int":
                self.in_int[idx] = int(value)
            elif kind == "double":
                self.in_double[idx] = float(value)
            elif value:
                self.in_bits |= 1 << idx
            else:
                self.in_bits &= ~(1 << idx)
        elif name == "input_bit_registers0_to_31":
            self.in_bits = (self.in_bits & ~0xFFFFFFFF) | int(value)
        elif name == "input_bit_registers32_to_63":
            self.in_bits = (self.in_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)
        else:
            self.inputs_misc[name] = value

    # -- event loop ---------------------------------------------------------------------

    def listen(self) -> None:
        for kind, port in (("rtde", RTDE_PORT), ("dash", DASHBOARD_PORT), ("script", SCRIPT_PORT)):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, port))
            except OSError as e:
                s.close()
                raise OSError(f"cannot bind {self.host}:{port}: {e.strerror or e}") from e
            s.listen(16)
            s.setblocking(False)
            self.sel.register(s, selectors.EVENT_READ, ("listen", kind))

    def run(self) -> None:
        os.set_blocking(0, False)
        os.set_blocking(self.out_fd, False)
        self.sel.register(0, selectors.EVENT_READ, ("parent_in", None))
        next_tick = time.monotonic() + self.period
        while self.running:
            timeout = max(0.0, next_tick - time.monotonic())
            for key, mask in self.sel.select(timeout):
                what, data = key.data
                if what == "listen":
                    self._accept(key.fileobj, data)  # type: ignore[arg-type]
                elif what == "parent_in":
                    self._read_parent()
                elif what == "parent_out":
                    self._flush_parent()
                else:
                    conn: _Conn = data
                    if mask & selectors.EVENT_READ:
                        self._on_readable(conn)
                    if mask & selectors.EVENT_WRITE and not conn.closed:
                        self._flush(conn)
                if not self.running:
                    break
            now = time.monotonic()
            if now >= next_tick:
                self.tick(now)
                next_tick += self.period
                if next_tick < now:
                    next_tick = now + self.period
        for conn in list(self.conns.values()):
            self._close(conn)
        for key in list(self.sel.get_map().values()):
            if key.data[0] == "listen":
                self.sel.unregister(key.fileobj)
                key.fileobj.close()  # type: ignore[union-attr]

    def tick(self, now: float) -> None:
        wall_dt = min(now - self.last_tick, 0.25)
        self.last_tick = now
        m = self.motion
        if self.time_scale > 0.0:
            dt = wall_dt / self.time_scale
        elif m is not None:
            dt = m.duration / 3.0 + 1e-9
        else:
            dt = wall_dt
        self.sim_time += dt
        if not self.safety_stopped:
            self.advance(dt)
        self._sync_q()
        self.control_step()
        for conn in list(self.conns.values()):
            if conn.kind == "rtde" and conn.started and not conn.closed:
                self._send_data(conn)
        self.settled_sent = not self.q_dirty and self.q_acked == self.q_seq
        for entry in self.pending_oks:
            entry[1] -= 1
            if entry[1] <= 0:
                self.to_parent({"t": "ok", "id": entry[0]})
        self.pending_oks = [e for e in self.pending_oks if e[1] > 0]

    def _accept(self, lsock: socket.socket, kind: str) -> None:
        try:
            sock, _addr = lsock.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        if kind == "rtde":
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Conn(kind, sock, self.next_cid)
        self.next_cid += 1
        self.conns[conn.cid] = conn
        self.sel.register(sock, selectors.EVENT_READ, ("conn", conn))
        log.debug("UR simulator %s: %s connection %d", self.host, kind, conn.cid)
        if kind == "dash":
            self._queue(conn, (WELCOME + "\n").encode())

    def _close(self, conn: _Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        with contextlib.suppress(KeyError, ValueError):
            self.sel.unregister(conn.sock)
        conn.sock.close()
        self.conns.pop(conn.cid, None)
        for name in [n for n, owner in self.input_owner.items() if owner == conn.cid]:
            del self.input_owner[name]

    def _queue(self, conn: _Conn, data: bytes) -> None:
        if conn.closed:
            return
        conn.outbuf += data
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        try:
            while conn.outbuf:
                n = conn.sock.send(conn.outbuf)
                del conn.outbuf[:n]
        except BlockingIOError:
            pass
        except OSError:
            self._close(conn)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.outbuf else 0)
        with contextlib.suppress(KeyError, ValueError):
            self.sel.modify(conn.sock, events, ("conn", conn))

    def _on_readable(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            log.debug("UR simulator %s: %s connection %d closed", self.host, conn.kind, conn.cid)
            self._close(conn)
            return
        conn.inbuf += data
        if conn.kind == "rtde":
            self._rtde_input(conn)
        elif conn.kind == "dash":
            self._dash_input(conn)
        else:
            self._script_input(conn)

    # -- RTDE -------------------------------------------------------------------------

    def _rtde_input(self, conn: _Conn) -> None:
        while len(conn.inbuf) >= 3 and not conn.closed:
            size, mtype = _HEADER.unpack_from(conn.inbuf)
            if size < 3:
                log.warning("UR simulator %s: bad RTDE header; closing", self.host)
                self._close(conn)
                return
            if len(conn.inbuf) < size:
                return
            payload = bytes(conn.inbuf[3:size])
            del conn.inbuf[:size]
            self._rtde_message(conn, mtype, payload)

    def _rtde_send(self, conn: _Conn, mtype: int, payload: bytes) -> None:
        self._queue(conn, _HEADER.pack(len(payload) + 3, mtype) + payload)

    def _rtde_message(self, conn: _Conn, mtype: int, payload: bytes) -> None:
        if mtype == _V:
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            ok = version in (1, 2)
            if ok:
                conn.protocol = version
            self._rtde_send(conn, _V, struct.pack(">B", 1 if ok else 0))
        elif mtype == _CV:
            self._rtde_send(conn, _CV, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif mtype == _O:
            self._setup_outputs(conn, payload)
        elif mtype == _I:
            self._setup_inputs(conn, payload)
        elif mtype == _S:
            conn.started = True
            self._rtde_send(conn, _S, b"\x01")
        elif mtype == _P:
            conn.started = False
            self._rtde_send(conn, _P, b"\x01")
        elif mtype == _U:
            self._data_from_client(conn, payload)
        elif mtype == _M:
            pass
        else:
            log.warning("UR simulator %s: unknown RTDE message type %d", self.host, mtype)

    @staticmethod
    def _names(raw: bytes) -> list[str]:
        return [n.strip() for n in raw.decode("ascii", "replace").split(",") if n.strip()]

    def _setup_outputs(self, conn: _Conn, payload: bytes) -> None:
        body = payload[8:] if conn.protocol >= 2 else payload
        names = self._names(body)
        types: list[str] = []
        getters: list[Callable[[], Any]] = []
        for name in names:
            typ = OUTPUT_TYPES.get(name)
            getter = self.output_getter(name) if typ is not None else None
            if typ is None or getter is None:
                types.append("NOT_FOUND")
                log.info("UR simulator %s: output %r NOT_FOUND", self.host, name)
            else:
                types.append(typ)
                getters.append(getter)
        if "NOT_FOUND" in types or not names:
            rid = 0
        else:
            rid = len(conn.outputs) + 1
            fmt = ">B" + "".join(_CODES[t] for t in types)
            conn.outputs.append((rid, struct.Struct(fmt), getters))
        log.debug("UR simulator %s: output recipe %d: %s", self.host, rid, names)
        self._rtde_send(conn, _O, struct.pack(">B", rid) + ",".join(types).encode())

    def _setup_inputs(self, conn: _Conn, payload: bytes) -> None:
        names = self._names(payload)
        types: list[str] = []
        for name in names:
            owner = self.input_owner.get(name)
            if name not in INPUT_TYPES:
                types.append("NOT_FOUND")
                log.info("UR simulator %s: input %r NOT_FOUND", self.host, name)
            elif owner is not None and owner != conn.cid:
                types.append("IN_USE")
            else:
                types.append(INPUT_TYPES[name])
        # Ids follow the order of requests whatever their outcome, as ur_rtde hard-codes them.
        rid = len(conn.inputs) + 1
        if all(t in _CODES for t in types) and names:
            for name in names:
                self.input_owner[name] = conn.cid
            fmt = ">" + "".join(_CODES[t] for t in types)
            conn.inputs[rid] = (struct.Struct(fmt), list(zip(names, types, strict=True)))
        else:
            conn.inputs[rid] = (struct.Struct(">"), [])
        log.debug("UR simulator %s: input recipe %d: %s -> %s", self.host, rid, names, types)
        self._rtde_send(conn, _I, struct.pack(">B", rid) + ",".join(types).encode())

    def _data_from_client(self, conn: _Conn, payload: bytes) -> None:
        if not payload:
            return
        rid = payload[0]
        recipe = conn.inputs.get(rid)
        if recipe is None or not recipe[1]:
            log.warning("UR simulator %s: data for unknown input recipe %d", self.host, rid)
            return
        st, fields = recipe
        if len(payload) - 1 != st.size:
            log.warning(
                "UR simulator %s: input recipe %d: %d bytes, expected %d",
                self.host,
                rid,
                len(payload) - 1,
                st.size,
            )
            return
        values = list(st.unpack_from(payload, 1))
        for name, typ in fields:
            n = 6 if typ.startswith("VECTOR6") else 3 if typ == "VECTOR3D" else 1
            chunk, values = values[:n], values[n:]
            self.set_input(name, chunk if n > 1 else chunk[0])

    def _send_data(self, conn: _Conn) -> None:
        if len(conn.outbuf) > 262144:
            return  # the client does not read; drop packages rather than block
        for rid, st, getters in conn.outputs:
            values = _flatten([g() for g in getters])
            body = st.pack(rid, *values)
            self._rtde_send(conn, _U, body)

    # -- dashboard ----------------------------------------------------------------------

    def _dash_input(self, conn: _Conn) -> None:
        while b"\n" in conn.inbuf and not conn.closed:
            raw, _, rest = conn.inbuf.partition(b"\n")
            conn.inbuf = bytearray(rest)
            line = raw.decode("utf-8", "replace").strip()
            reply, close = self.dashboard(line)
            self._queue(conn, (reply + "\n").encode())
            if close:
                self._flush(conn)
                self._close(conn)
        if len(conn.inbuf) > 4096:
            self._close(conn)

    def dashboard(self, line: str) -> tuple[str, bool]:
        cmd = line.lower()
        running = self.runtime_state == PLAYING
        prog = self.program_name or "<unnamed>"
        if line == "PolyscopeVersion":
            return POLYSCOPE_VERSION, False
        if cmd == "get serial number":
            return self.serial, False
        if cmd == "get robot model":
            return ROBOT_MODEL, False
        if cmd == "is in remote control":
            return "true", False
        if cmd == "get operational mode":
            return "NONE", False
        if cmd == "stop":
            if self.runtime_state != STOPPED:
                self.stop_program()
            return "Stopped", False
        if cmd == "play":
            if self.safety_stopped or self.robot_mode != RUNNING:
                return "Failed to execute: play", False
            if self.runtime_state == PAUSED and self.control_loaded:
                self.runtime_state = PLAYING
                return "Starting program", False
            if self.program_name == "rtde_control":
                self._start_control_loop()
                return "Starting program", False
            return "Failed to execute: play", False
        if cmd == "pause":
            if running:
                self.halt()
                self.runtime_state = PAUSED
                return "Pausing program", False
            return "Failed to execute: pause", False
        if cmd == "running":
            return f"Program running: {'true' if running else 'false'}", False
        if cmd == "programstate":
            return f"{_RUNTIME_NAMES.get(self.runtime_state, 'STOPPED')} {prog}", False
        if cmd == "get loaded program":
            if self.program_name:
                return f"Loaded program: {self.program_name}", False
            return "No program loaded", False
        if cmd == "power on":
            if self.robot_mode == POWER_OFF:
                self.robot_mode = IDLE
            return "Powering on", False
        if cmd == "power off":
            self.stop_program()
            self.robot_mode = POWER_OFF
            return "Powering off", False
        if cmd == "brake release":
            if self.robot_mode != POWER_OFF:
                self.robot_mode = RUNNING
            return "Brake releasing", False
        if cmd == "robotmode":
            return f"Robotmode: {_ROBOT_MODE_NAMES.get(self.robot_mode, 'RUNNING')}", False
        if cmd == "safetystatus":
            return f"Safetystatus: {self.safety_name()}", False
        if cmd == "safetymode":
            return f"Safetymode: {self.safety_name()}", False
        if cmd == "unlock protective stop":
            self.set_protective(False)
            return "Protective stop releasing", False
        if cmd == "close popup":
            return "closing popup", False
        if cmd == "close safety popup":
            return "closing safety popup", False
        if cmd.startswith("popup "):
            return "showing popup", False
        if cmd.startswith("addtolog "):
            return "Added log message", False
        if cmd == "quit":
            return "Disconnected", True
        return f"could not understand: '{line}'", False

    # -- script port --------------------------------------------------------------------

    def _script_input(self, conn: _Conn) -> None:
        while b"\n" in conn.inbuf:
            raw, _, rest = conn.inbuf.partition(b"\n")
            conn.inbuf = bytearray(rest)
            line = raw.decode("utf-8", "replace").rstrip("\r")
            if conn.program is None:
                m = re.match(r"(def|sec)\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(\s*\)\s*:", line)
                if m is not None:
                    conn.program = [line]
                    conn.program_name = m.group(2) if m.group(1) == "def" else ""
                elif line.strip():
                    log.info("UR simulator %s: script line ignored: %.80s", self.host, line)
                continue
            conn.program.append(line)
            if line == "end":
                text = "\n".join(conn.program) + "\n"
                name = conn.program_name
                conn.program = None
                if name:
                    log.debug("UR simulator %s: program %r (%d bytes)", self.host, name, len(text))
                    self.load_program(name, text)


def _child_main(cfg_json: str) -> int:
    """Entry point of the child process (see the module docstring)."""
    cfg = json.loads(cfg_json)
    # Keep the protocol pipe private: stray prints go to stderr.
    out_fd = os.dup(1)
    os.dup2(2, 1)
    logging.basicConfig(
        level=int(cfg.get("log_level", logging.WARNING)),
        format="%(asctime)s %(levelname)s [ur-sim %(process)d] %(message)s",
        stream=sys.stderr,
    )
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    ctl = _Controller(cfg, out_fd)
    try:
        ctl.listen()
    except OSError as e:
        os.write(out_fd, (json.dumps({"t": "error", "msg": str(e)}) + "\n").encode())
        return 1
    os.write(out_fd, b'{"t": "listening"}\n')
    ctl.run()
    return 0
