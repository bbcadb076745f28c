"""The KUKA controller behind the KUKAVARPROXY twin: its KRL variables and cellcal's KRL
loop running on it — no sockets (``mocks/kuka/kvp_server.py`` decodes the requests).

Variables (names case-insensitive, as in KRL), as a KR C4 running the shipped
``CellCal.src`` shows them through KUKAVARPROXY:

* ``$AXIS_ACT_MEAS`` (E6AXIS, read only: the encoders; ``$AXIS_ACT`` the same),
  ``$MODE_OP`` (``#T1``, ``#T2``, ``#AUT``, ``#EX``), ``$PERI_RDY`` (drives on),
  ``$STOPMESS``, ``$PRO_STATE1`` (``#P_ACTIVE`` while the loop runs, ``#P_STOP`` after a
  stop message), ``$ROB_STOPPED``, ``$ROBNAME[]`` (text in quotes), ``$KR_SERIALNO``;
  all read only;
* the loop's ``CC_TARGET`` (E6AXIS), ``CC_SEQ``, ``CC_ACK`` (INT), ``CC_SPEED`` (INT,
  1..100 % of the axis speeds), ``CC_STOP`` (BOOL) — read/write outside T1/T2 (the twin
  refuses writes in the manual modes: the mode a cell is set up in, where the loop must
  not be commanded from outside).

A read of another name, a write of a read-only variable or of text that is not the
variable's type fails (the reply's ok byte 0, no value), as the proxy answers. A write's
reply carries the value after the write.

The loop (evaluated at every request, so a client that polls sees it move): when
``CC_SEQ <> CC_ACK``, the mode is AUT or EX, the drives are on and no stop message is
active, it moves ``PTP CC_TARGET`` — the shared motion model's synchronised move at
``CC_SPEED`` % of ``joint_speed_deg_s``, times ``time_scale`` in wall seconds (0:
arrives at once) — and on arrival sets ``CC_ACK`` to the ``CC_SEQ`` it read when the
move started (a number written during the move is the next request, not this one's
answer). A target outside the joint limits raises a stop message (``$STOPMESS`` TRUE,
``$PRO_STATE1`` ``#P_STOP``) and is not executed. Drives switched off during a move brake
it where it is; it resumes when they are back. ``CC_STOP = TRUE`` brakes the move where
it is, abandons it (``CC_ACK`` as on arrival) and resets ``CC_STOP``.

Faults (:class:`KrcFaults`, settable at run time): the mode, the drives, ``no_ack`` (the
loop hangs: nothing is executed or acknowledged), ``stop_every`` (every N-th move raises a
stop message instead of moving — the simulated cell's ``robot_protective_stop_every``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers.kuka_kvp_wire import (
    KrlTextError,
    format_axes,
    parse_axes,
    parse_bool,
    parse_int,
)
from cellcal.mocks.motion import JointMove
from cellcal.mocks.twins import limits_deg

if TYPE_CHECKING:
    from cellcal.mocks.simulated_cell import SimulatedCell

MANUAL = ("#T1", "#T2")
MODES = ("#T1", "#T2", "#AUT", "#EX")
LOOP_VARS = ("CC_TARGET", "CC_SEQ", "CC_ACK", "CC_SPEED", "CC_STOP")


@dataclass
class KrcFaults:
    mode: str = "#EX"
    drives_on: bool = True
    no_ack: bool = False
    stop_every: int = 0  # every N-th move ends in a stop message before it starts (0: never)


def _bool(value: bool) -> str:
    return "TRUE" if value else "FALSE"


def _real(value: float) -> str:
    """A REAL as KRL shows it: single precision, up to 7 significant digits."""
    text = f"{float(np.float32(value)):.7g}"
    return text if any(c in text for c in ".e") else text + ".0"


class KrcController:
    """The controller's variables and loop; every method is called under the server's
    lock (``lock``), one request at a time."""

    def __init__(
        self,
        *,
        q0_deg: list[float],
        limits_deg: list[tuple[float, float]],
        joint_speed_deg_s: float,
        time_scale: float,
        robot_name: str = "KR5ARC",
        serial: int = 940001,
        faults: KrcFaults | None = None,
        on_move: Callable[[Array], None] | None = None,
    ) -> None:
        self.lock = threading.Lock()
        self.q = np.asarray(q0_deg, dtype=np.float64)
        self.limits = limits_deg
        self.joint_speed = joint_speed_deg_s
        self.time_scale = time_scale
        self.robot_name = robot_name
        self.serial = serial
        self.faults = faults or KrcFaults()
        self.on_move = on_move
        self.target = self.q.copy()
        self.seq = self.ack = 0
        self.speed = 10
        self.stop_requested = False
        self.stop_message = False
        self.move: JointMove | None = None
        self.move_seq = 0  # the CC_SEQ the running move answers (read when it started)
        self.moves_started = 0
        self.move_started = 0.0
        self.requests: list[tuple[int, str, str | None]] = []

    # ------------------------------------------------------------------ variables

    def read(self, name: str) -> str | None:
        """A variable's text, or None when there is no such variable."""
        self.step()
        key = name.upper()
        values: dict[str, Callable[[], str]] = {
            "$AXIS_ACT_MEAS": self._axis_text,
            "$AXIS_ACT": self._axis_text,
            "$MODE_OP": lambda: self.faults.mode,
            "$PERI_RDY": lambda: _bool(self.faults.drives_on),
            "$STOPMESS": lambda: _bool(self.stop_message),
            "$PRO_STATE1": lambda: "#P_STOP" if self.stop_message else "#P_ACTIVE",
            "$ROB_STOPPED": lambda: _bool(self.move is None),
            "$ROBNAME[]": lambda: f'"{self.robot_name}"',
            "$KR_SERIALNO": lambda: str(self.serial),
            "CC_TARGET": lambda: format_axes(list(self.target)),
            "CC_SEQ": lambda: str(self.seq),
            "CC_ACK": lambda: str(self.ack),
            "CC_SPEED": lambda: str(self.speed),
            "CC_STOP": lambda: _bool(self.stop_requested),
        }
        get = values.get(key)
        return None if get is None else get()

    def write(self, name: str, text: str) -> str | None:
        """Write a variable; its text after the write, or None when refused."""
        key = name.upper()
        if key not in LOOP_VARS or self.faults.mode in MANUAL:
            return None
        try:
            if key == "CC_TARGET":
                self.target = np.array(parse_axes(text, key), dtype=np.float64)
            elif key in ("CC_SEQ", "CC_ACK"):
                setattr(self, key[3:].lower(), parse_int(text, key))
            elif key == "CC_SPEED":
                speed = parse_int(text, key)
                if not 1 <= speed <= 100:
                    return None
                self.speed = speed
            else:
                self.stop_requested = parse_bool(text, key)
        except KrlTextError:
            return None
        self.step()
        return self.read(key)

    def _axis_text(self) -> str:
        q = self.q_now()
        parts = [f"A{i + 1} {_real(v)}" for i, v in enumerate(q)]
        parts += [f"E{i + 1} 0.0" for i in range(6)]
        return "{E6AXIS: " + ", ".join(parts) + "}"

    # ------------------------------------------------------------------ the loop

    def q_now(self) -> Array:
        """Where the axes are now (deg): on the way when a move runs."""
        if self.move is None:
            return self.q
        t = (time.monotonic() - self.move_started) / self.time_scale if self.time_scale else 1e9
        q, _ = self.move.at(t)
        return q

    def _can_move(self) -> bool:
        f = self.faults
        return f.mode not in MANUAL and f.drives_on and not self.stop_message and not f.no_ack

    def step(self) -> None:
        """Advance the loop to now."""
        if self.move is not None:
            if not self.faults.drives_on:  # braked where it is; resumes with the drives
                self.q, self.move = self.q_now().copy(), None
                if self.on_move is not None:
                    self.on_move(np.radians(self.q))
                return
            if self.stop_requested:
                self._arrive(self.q_now())
                return
            t = (time.monotonic() - self.move_started) / self.time_scale if self.time_scale else 1e9
            if self.move.done(t):
                self._arrive(self.move.q1)
            return
        if self.stop_requested:
            self.stop_requested = False
            self.ack = self.seq
            return
        if self.seq == self.ack or not self._can_move():
            return
        target = self.target
        inside = all(lo <= v <= hi for v, (lo, hi) in zip(target, self.limits, strict=True))
        self.moves_started += 1
        every = self.faults.stop_every
        if not inside or (every and self.moves_started % every == 0):
            self.stop_message = True
            return
        speed = self.joint_speed * self.speed / 100.0
        self.move = JointMove(self.q.copy(), target.copy(), speed)
        self.move_seq = self.seq
        self.move_started = time.monotonic()
        self.step()

    def _arrive(self, q: Array) -> None:
        self.q = np.asarray(q, dtype=np.float64).copy()
        self.move = None
        self.stop_requested = False
        self.ack = self.move_seq
        if self.on_move is not None:
            self.on_move(np.radians(self.q))

    def acknowledge_stop_message(self) -> None:
        """What the operator's acknowledgement on the pendant does."""
        self.stop_message = False


def krc_for_cell(home_deg: list[float], cell: SimulatedCell, time_scale: float) -> KrcController:
    """The simulated cell's robot as a KRC running cellcal's loop: its home, joint limits
    and speed; the cell follows its moves."""
    return KrcController(
        q0_deg=list(home_deg),
        limits_deg=limits_deg(cell),
        joint_speed_deg_s=math.degrees(cell.joint_speed),
        time_scale=time_scale,
        robot_name=cell.model.name.upper(),
        faults=KrcFaults(stop_every=cell.faults.robot_protective_stop_every),
        on_move=cell.set_q,
    )
