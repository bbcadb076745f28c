"""The state of the simulated UR controller (child process, no sockets): robot mode,
safety, the program and runtime state, registers and I/O, the motion, and the control
loop of ur_rtde's ``rtde_control`` script. The child's loop calls :meth:`Controller.step`
once per controller cycle (2 ms, 500 Hz) and sends the outputs after it.

The control loop follows ur_rtde's ``rtde_control.script``: ``output_int_register_0`` is 1
when ready and 2 when done with a command; the command is ``input_int_register_0`` (1
moveJ, 2 moveJ_IK, 3 moveL, 4 moveL_FK, 31 protective stop, 33 stopL, 34 stopJ, 255 stop
script) with values in ``input_double_register_0..7`` and ``async`` in
``input_int_register_1``; a clear (0) makes it ready again. Asynchronous moves report in
``output_int_register_2`` with the script's bit layout (running bit 15, progress bits
0-14, change counter bits 16-22, operation id bits 24-30). The loop is simulated, not
interpreted.

Kinematics live in the parent process (see :mod:`cellcal.mocks.ur.server`): the
controller reports each new joint position (``q``, with its velocity), the parent
answers with the TCP pose and speed (``pose``) after calling its ``on_move``, and the
controller asks for ``ik`` when a move needs it. The outputs carry the last acknowledged
joint position with its pose (so actual_q and actual_TCP_pose always agree, at the cost
of a cycle of lag), and a synchronous move is reported done only after a package with
the final position has gone out, so ``on_move`` has seen it before ``moveJ`` returns.

Simplifications (docs/ur-twin.md): motion is :class:`cellcal.mocks.motion.JointMove`,
timed on the leading joint (moveJ, moveL_FK) or the TCP translation (moveL; a pure
reorientation on the leading joint at 1.05 rad/s, 1.4 rad/s²), straight in joint space.
A protective or emergency stop halts the robot and aborts the move; the script stays
PLAYING but takes no command until the stop is cleared (at once: no 5 s wait). A joint
target outside the joint ranges (±360°) is a protective stop before any motion. An
unreachable pose ends the control script, as ``get_inverse_kin``'s runtime error does.
Other commands are acknowledged without effect; other scripts end at once; a loaded
``.urp`` runs without effect until stopped. ``time_scale`` (wall seconds per simulated
second; 0: every move ends in three cycles) scales motion only.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellcal.mocks.motion import JointMove
from cellcal.mocks.ur.fields import Fields
from cellcal.mocks.ur.rtde_codec import CYCLE_S

log = logging.getLogger("cellcal.mocks.ur")

# Runtime states, robot modes, safety modes and bits (UR's and ur_rtde's numbering)
STOPPING, STOPPED, PLAYING, PAUSED = 0, 1, 2, 4
RUNTIME_NAMES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED"}
POWER_OFF, IDLE, RUNNING = 3, 5, 7
ROBOT_MODE_NAMES = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 7: "RUNNING"}
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
SAFETY_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}
BIT_NORMAL_MODE = 0
BIT_PROTECTIVE_STOPPED = 2
BIT_ROBOT_EMERGENCY_STOPPED = 6
BIT_EMERGENCY_STOPPED = 7
BIT_STOPPED_DUE_TO_SAFETY = 10

# Control-script protocol (rtde_control.script)
READY, DONE = 1, 2
CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_MOVEL_FK = 1, 2, 3, 4
CMD_PROTECTIVE_STOP, CMD_STOPL, CMD_STOPJ, CMD_STOP_SCRIPT = 31, 33, 34, 255
CONTROL_SCRIPT = "rtde_control"

#: A UR e-Series joint turns ±360° (every joint, UR3e to UR20): a target beyond is
#: refused with a protective stop, as the controller's joint position limits do.
JOINT_RANGE_RAD = 2.0 * math.pi

SAFETY_REPLY_CYCLES = 3  # a safety request is answered this many cycles after it
STOPPING_CYCLES = 25  # a program that ends by itself is STOPPING for 50 ms


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


class Controller:
    """The simulated controller's state and control loop (see the module docstring)."""

    def __init__(self, cfg: dict[str, Any], to_parent: Callable[[dict[str, Any]], None]) -> None:
        self.host: str = cfg["host"]
        self.time_scale = float(cfg["time_scale"])
        self.serial = str(cfg["serial"])
        self.to_parent = to_parent
        self.cycle = 0  # controller cycles since start; timestamp = cycle × 2 ms
        self.q: list[float] = [float(x) for x in cfg["q0"]]  # where the joints are
        self.qd = [0.0] * 6
        # What clients are told: the last position the parent acknowledged, with its pose.
        self.q_pub = list(self.q)
        self.qd_pub = [0.0] * 6
        self.qdd_pub = [0.0] * 6
        self.q_sent = list(self.q)
        self.qd_sent = [0.0] * 6
        self.tcp: list[float] = [float(x) for x in cfg["pose0"]]
        self.tcp_speed = [0.0] * 6
        self.runtime_state = STOPPED
        self.stopping_left = 0  # cycles until STOPPING becomes STOPPED
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
        self.speed_fraction = 1.0
        self.digital_outputs = 0
        self.analog_outputs = [0.0, 0.0]
        self.payload = 0.0
        self.motion: JointMove | None = None
        self.motion_t = 0.0
        self.motion_async = False
        self.program_name = ""  # the program running or last run (a script's name)
        self.loaded_program = ""  # the .urp file loaded through the dashboard
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
        self.fields = Fields(self)

    # -- parent link --------------------------------------------------------------------

    def on_parent(self, msg: dict[str, Any]) -> bool:
        """Handle a message of the parent; False for ``quit``."""
        t = msg.get("t")
        if t == "pose":
            if int(msg["seq"]) == self.q_seq:
                self.q_acked = self.q_seq
                self.q_pub = self.q_sent
                self.qd_pub = self.qd_sent
                self.tcp = [float(x) for x in msg["pose"]]
                self.tcp_speed = [float(x) for x in msg.get("speed", [0.0] * 6)]
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
            self.pending_oks.append([int(msg["id"]), SAFETY_REPLY_CYCLES])
        elif t == "quit":
            return False
        return True

    def _sync_q(self) -> None:
        if self.q_dirty and self.q_acked == self.q_seq:
            self.q_seq += 1
            self.q_dirty = False
            self.q_sent = list(self.q)
            self.qd_sent = list(self.qd)
            self.to_parent({"t": "q", "seq": self.q_seq, "q": self.q_sent, "qd": self.qd_sent})

    @property
    def settled(self) -> bool:
        """The parent has seen the current joint position (on_move called, TCP pose
        known) and a data package with both has gone to every client. "Done" waits for
        this, so a client reading another connection after a move sees the end state."""
        return not self.q_dirty and self.q_acked == self.q_seq and self.settled_sent

    # -- the cycle ------------------------------------------------------------------------

    def step(self) -> None:
        """One controller cycle, before the outputs go out."""
        self.cycle += 1
        m = self.motion
        if self.time_scale > 0.0:
            dt = CYCLE_S / self.time_scale
        elif m is not None:
            dt = m.duration / 3.0 + 1e-9
        else:
            dt = CYCLE_S
        if not self.safety_stopped:
            self.advance(dt)
        if self.runtime_state == STOPPING:
            self.stopping_left -= 1
            if self.stopping_left <= 0:
                self.runtime_state = STOPPED
        self._sync_q()
        self.control_step()

    def after_outputs(self) -> None:
        """The cycle's outputs have gone out."""
        self.settled_sent = not self.q_dirty and self.q_acked == self.q_seq
        for entry in self.pending_oks:
            entry[1] -= 1
            if entry[1] <= 0:
                self.to_parent({"t": "ok", "id": entry[0]})
        self.pending_oks = [e for e in self.pending_oks if e[1] > 0]

    # -- motion and safety ------------------------------------------------------------

    def halt(self) -> None:
        if (self.motion is not None and self.motion_async) or self.async_finish_pending:
            self._write_async(-1)
        self.motion = None
        self.async_finish_pending = False
        self.qd = [0.0] * 6

    @property
    def safety_stopped(self) -> bool:
        return self.protective or self.emergency

    def set_protective(self, on: bool) -> None:
        if on and not self.protective:
            log.info("UR twin %s: protective stop", self.host)
            self._safety_halt()
        self.protective = on

    def set_emergency(self, on: bool) -> None:
        if on and not self.emergency:
            log.info("UR twin %s: emergency stop", self.host)
            self._safety_halt()
        self.emergency = on

    def _safety_halt(self) -> None:
        self.halt()
        # The command in progress is abandoned without "done": ur_rtde sees the safety
        # bits and returns False, then clears the command.
        self.pending = None

    def start_motion(
        self, q1: list[float], v: float, a: float, is_async: bool, cart_m: float | None
    ) -> bool:
        """Move to ``q1``. Joint moves are timed on the leading joint (v rad/s, a rad/s²);
        linear moves (``cart_m``, the TCP translation) on the TCP (v m/s, a m/s²), or, for
        a pure reorientation, on the leading joint at 1.05 rad/s and 1.4 rad/s². A target
        outside the joint ranges (±360°, :data:`JOINT_RANGE_RAD`) is not moved to: a
        protective stop, as the controller's joint position limits give; False then."""
        q0, q1_ = np.asarray(self.q, dtype=np.float64), np.asarray(q1, dtype=np.float64)
        beyond = np.flatnonzero(~(np.abs(q1_) <= JOINT_RANGE_RAD + 1e-9))
        if len(beyond):
            j = int(beyond[0])
            log.warning(
                "UR twin %s: joint %d target %.6g° is outside its range ±360°: protective stop",
                self.host,
                j + 1,
                math.degrees(float(q1_[j])),
            )
            self.set_protective(True)
            return False
        if cart_m is not None and cart_m > 1e-9:
            self.motion = JointMove(q0, q1_, v, a, distance=cart_m)
        elif cart_m is not None:
            self.motion = JointMove(q0, q1_, 1.05, 1.4)
        else:
            self.motion = JointMove(q0, q1_, v, a)
        self.motion_t = 0.0
        self.motion_async = is_async
        if is_async:
            self._write_async(0)
        return True

    def advance(self, dt: float) -> None:
        m = self.motion
        if m is None:
            self.qdd_pub = [0.0] * 6
            return
        self.motion_t += dt
        q_arr, qd_arr = m.at(self.motion_t)
        q, qd = q_arr.tolist(), qd_arr.tolist()
        if q != self.q:
            self.q = q
            self.q_dirty = True
        self.qdd_pub = [(b - a) / dt for a, b in zip(self.qd, qd, strict=True)]
        self.qd = qd
        if m.done(self.motion_t):
            self.motion = None
            self.qd = [0.0] * 6
            if self.motion_async:
                self.async_finish_pending = True

    # -- programs ---------------------------------------------------------------------

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

    def can_run(self) -> bool:
        return self.robot_mode == RUNNING and not self.safety_stopped

    def run_script(self, name: str, text: str) -> None:
        """A program received on the script port (``def name(): ... end``)."""
        if not self.can_run():
            log.warning(
                "UR twin %s: program %r not started (robot mode %s, safety %s)",
                self.host,
                name,
                ROBOT_MODE_NAMES.get(self.robot_mode, self.robot_mode),
                self.safety_name(),
            )
            return
        self.halt()
        self.program_name = name
        if name == CONTROL_SCRIPT:
            self.start_control_loop()
        else:
            log.info("UR twin %s: program %r run (no effect simulated)", self.host, name)
            self.end_program()

    def play_loaded(self) -> None:
        """Dashboard ``play`` of the loaded .urp: it runs (no effect) until stopped."""
        self.halt()
        self.program_name = self.loaded_program.rsplit("/", 1)[-1]
        self.control_loaded = False
        self.pending = None
        self.runtime_state = PLAYING

    def start_control_loop(self) -> None:
        self.control_loaded = True
        self.runtime_state = PLAYING
        self.executing = False
        self.pending = None
        self._write_async(-1)
        self.out_int[0] = READY

    def stop_program(self) -> None:
        """Stopped from outside (dashboard ``stop``, power off): STOPPED at once."""
        self.halt()
        self.pending = None
        self.control_loaded = False
        self.runtime_state = STOPPED

    def end_program(self) -> None:
        """The program ends by itself (its last statement, a runtime error): it is
        STOPPING for a few cycles, then STOPPED. ur_rtde relies on that window: it stops
        its script through RTDE, waits for the program-running bit to clear, then asks
        the dashboard to ``stop``, and fails unless the answer is ``Stopped``."""
        self.stop_program()
        self.runtime_state = STOPPING
        self.stopping_left = STOPPING_CYCLES

    # -- control loop (rtde_control.script) ------------------------------------------

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
            if self.start_motion(vals, v, a, is_async, None):
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
            log.info("UR twin %s: control script stopped by the client", self.host)
            self.end_program()
        else:
            log.info("UR twin %s: command %d acknowledged, not simulated", self.host, cmd)
            self.out_int[0] = DONE

    def _after_start(self, is_async: bool) -> None:
        if is_async:
            self.out_int[0] = DONE
        else:
            self.pending = _Pending("move", CMD_MOVEJ)

    def _stop_async_move(self) -> None:
        if self.motion is not None and self.motion_async:
            self.halt()

    def _on_ik_reply(self, rid: int, q: list[float] | None) -> None:
        p = self.pending
        if p is None or p.kind != "ik" or p.ik_id != rid:
            return  # abandoned (safety stop, script stopped)
        self.pending = None
        if q is None:
            log.warning(
                "UR twin %s: no inverse kinematics for pose %s; the control script ends",
                self.host,
                [round(x, 6) for x in p.pose],
            )
            self.end_program()
            return
        self._stop_async_move()
        q1 = [float(x) for x in q]
        cart = math.dist(self.tcp[:3], p.pose[:3]) if p.cmd == CMD_MOVEL else None
        if self.start_motion(q1, p.v, p.a, p.is_async, cart):
            self._after_start(p.is_async)

    # -- status words -------------------------------------------------------------------

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
        return SAFETY_NAMES[self.safety_mode()]

    def robot_status_bits(self) -> int:
        bits = 0
        if self.robot_mode != POWER_OFF:
            bits |= 1
        if self.runtime_state == PLAYING:
            bits |= 2
        return bits
