"""The UR twin, parent side: :class:`URTwin` starts the simulated Universal Robots
controller (PolyScope 5.11, e-Series) in a child process and keeps its kinematics and the
``on_move`` hook here; :func:`serve` is the twin of mock mode (``cellcal/families.py``),
:func:`twin_for_cell` builds it for a simulated cell (``serve`` and ``cellcal mock
ur``). The unmodified ur_rtde (``rtde_control``, ``rtde_receive``) and UR's own RTDE client
drive it; what it serves is in docs/ur-twin.md.

Where the rest lives:

* :mod:`cellcal.mocks.ur.child`: the child process (one selector loop, 2 ms cycles) and
  why there is one;
* :mod:`cellcal.mocks.ur.controller`: controller state, control loop, motion,
  simplifications;
* :mod:`cellcal.mocks.ur.rtde_codec`, :mod:`cellcal.mocks.ur.rtde_session`,
  :mod:`cellcal.mocks.ur.fields`: RTDE (30004) framing, connections, the field table;
* :mod:`cellcal.mocks.ur.dashboard`: the dashboard server (29999);
* :mod:`cellcal.mocks.ur.script_port`: URScript in and the real-time state out (30003).

The parent and the child talk JSON lines over the child's stdin/stdout: the child
reports each new joint position and velocity (``q``), the parent answers with the TCP
pose and speed (``pose``) after calling ``on_move``; the child asks for ``ik`` when a move
needs it (``ikr`` answers, None when unreachable); ``safety`` requests are answered
(``ok``) a few cycles after the new state went out.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cellcal.calib.rotations import matrix_from_rotvec, rotvec_from_matrix
from cellcal.mocks.twins import UR_HOSTS, RunningTwin
from cellcal.mocks.ur.dashboard import POLYSCOPE_VERSION

if TYPE_CHECKING:
    from cellcal.drivers.ur import UROptions
    from cellcal.mocks.simulated_cell import SimulatedCell

__all__ = ["POLYSCOPE_VERSION", "CellInURUnits", "URKinematics", "URTwin", "serve"]

log = logging.getLogger("cellcal.mocks.ur")

Vec = NDArray[np.float64]

DEFAULT_SERIAL = "20215500001"


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
        return np.concatenate([T[:3, 3] / 1000.0, rotvec_from_matrix(T[:3, :3])])

    def ik(self, pose: np.ndarray, q_seed: np.ndarray) -> np.ndarray | None:
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            return None
        T = np.eye(4)
        T[:3, :3] = matrix_from_rotvec(pose[3:6])
        T[:3, 3] = pose[:3] * 1000.0
        return self.cell.joints_for(T, q_seed)


class URTwin:
    """A simulated UR controller on ``host``:30004/29999/30003 (see docs/ur-twin.md).

    ``on_move(q)`` is called from the twin's reader thread each time the joints
    change (at most once per RTDE cycle; always with the final position of a move)."""

    def __init__(
        self,
        kinematics: URKinematics,
        *,
        q0: np.ndarray,
        time_scale: float = 0.0,
        on_move: Callable[[np.ndarray], None] | None = None,
        serial_number: str = DEFAULT_SERIAL,
        start_timeout_s: float = 15.0,
    ) -> None:
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape != (6,) or not np.all(np.isfinite(q0)):
            raise ValueError("q0 must be 6 finite joint positions (rad)")
        if not (math.isfinite(time_scale) and time_scale >= 0.0):
            raise ValueError("time_scale must be >= 0")
        if not serial_number.isdigit():
            raise ValueError("serial_number must be digits (ur_rtde checks it is a number)")
        self.kinematics = kinematics
        self.time_scale = float(time_scale)
        self.on_move = on_move
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
            raise RuntimeError("twin already started")
        pose0 = np.asarray(self.kinematics.fk(self._q), dtype=np.float64)
        self._pose = pose0
        cfg = {
            "host": host,
            "q0": self._q.tolist(),
            "pose0": pose0.tolist(),
            "time_scale": self.time_scale,
            "serial": self.serial_number,
            "log_level": logging.getLogger("cellcal").getEffectiveLevel(),
        }
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        code = "import sys; from cellcal.mocks.ur.child import child_main; "
        code += "sys.exit(child_main(sys.argv[1]))"
        self._listening.clear()
        self._is_listening = False
        self._start_error = None
        # -P: the cellcal of PYTHONPATH (the parent's), not one in the working directory
        self._proc = subprocess.Popen(
            [sys.executable, "-P", "-c", code, json.dumps(cfg)],
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
            raise OSError(f"UR twin on {host}: {err}")

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

    def __enter__(self) -> URTwin:
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
            log.warning("UR twin %s: cannot reach the child process: %s", self.host, e)

    def _request(self, msg: dict[str, Any], timeout: float = 5.0) -> None:
        if self._proc is None:
            raise RuntimeError("twin not started")
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
            raise RuntimeError(f"UR twin {self.host}: no answer to {msg['t']}")

    def _read_child(self) -> None:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        for raw in proc.stdout:
            try:
                msg = json.loads(raw)
            except ValueError:
                log.warning("UR twin %s: bad line from child: %r", self.host, raw[:200])
                continue
            t = msg.get("t")
            if t == "q":
                q = np.asarray(msg["q"], dtype=np.float64)
                self._on_q(int(msg["seq"]), q, np.asarray(msg.get("qd", np.zeros(6)), float))
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
            self._start_error = "the twin's process ended before listening"
        self._listening.set()

    def _on_q(self, seq: int, q: Vec, qd: Vec) -> None:
        try:
            pose = np.asarray(self.kinematics.fk(q), dtype=np.float64)
            if pose.shape != (6,) or not np.all(np.isfinite(pose)):
                raise ValueError(f"fk returned {pose!r}")
            speed = self._tcp_speed(q, qd, pose)
        except Exception:
            log.exception("UR twin %s: fk failed; the TCP pose is stale", self.host)
            pose, speed = self.tcp_pose, np.zeros(6)
        with self._lock:
            self._q = q.copy()
            self._pose = pose
        if self.on_move is not None:
            try:
                self.on_move(q.copy())
            except Exception:
                log.exception("UR twin %s: on_move failed", self.host)
        self._send({"t": "pose", "seq": seq, "pose": pose.tolist(), "speed": speed.tolist()})

    def _tcp_speed(self, q: Vec, qd: Vec, pose: Vec) -> Vec:
        """The TCP's twist [m/s, rad/s] in the base frame at joint velocity ``qd``."""
        if not np.any(qd):
            return np.zeros(6)
        h = 1e-4
        ahead = np.asarray(self.kinematics.fk(q + qd * h), dtype=np.float64)
        turn = matrix_from_rotvec(ahead[3:]) @ matrix_from_rotvec(pose[3:]).T
        return np.concatenate([(ahead[:3] - pose[:3]) / h, rotvec_from_matrix(turn) / h])

    def _on_ik(self, rid: int, pose: list[float], seed: list[float]) -> None:
        q: np.ndarray | None
        try:
            q = self.kinematics.ik(np.asarray(pose, float), np.asarray(seed, float))
            if q is not None:
                q = np.asarray(q, dtype=np.float64)
                if q.shape != (6,) or not np.all(np.isfinite(q)):
                    q = None
        except Exception:
            log.exception("UR twin %s: ik failed", self.host)
            q = None
        self._send({"t": "ikr", "id": rid, "q": None if q is None else q.tolist()})


def twin_for_cell(
    cell: SimulatedCell, home_deg: list[float] | tuple[float, ...], time_scale: float
) -> URTwin:
    """The twin of a cell's UR controller: the cell's nominal kinematics in UR's units,
    starting at ``home_deg``, reporting every move to the cell (not started yet)."""
    return URTwin(
        CellInURUnits(cell),
        q0=np.radians(np.asarray(home_deg, dtype=np.float64)),
        time_scale=time_scale,
        on_move=cell.set_q,
    )


def serve(options: UROptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of a configured UR controller: the first free loopback address of its
    range (the ports are fixed), the simulated cell's nominal kinematics in UR's units."""
    from cellcal.errors import DeviceError

    last: Exception | None = None
    for host in UR_HOSTS:
        sim = twin_for_cell(cell, options.home_deg, time_scale)
        try:
            sim.start(host)
        except OSError as exc:  # another simulated UR holds this address's fixed ports
            last = exc
            continue
        return RunningTwin(options.model_copy(update={"address": host}), sim)
    raise DeviceError(f"no free loopback address for a simulated UR ({last})")
