"""The move → settle → read contract every stop-and-measure robot meets, once:
:class:`StopAndMeasureRobot` (``move_joints`` for every family, UR's included) and
:class:`HandshakeRobot` (the families that command a program on their controller).

A campaign moves the robot to a joint target, waits for it to stand still there, and
measures; the joints it records are the controller's measured ones, read after the move
is known finished — never the set-point. Every robot family that moves through a
program on its controller and a handshake (a target, a sequence number the program
acknowledges once it stands still: the Modbus map, KUKA's KRL loop, ABB's RAPID module)
subclasses :class:`HandshakeRobot`, which holds the contract's logic; a family supplies
only its transport:

* ``_open`` / ``_close``: the link;
* ``_state``: one reading of the controller (:class:`ControllerState`): why it cannot
  take a move now (operating mode, drives, a stop or an error), whether a running move
  has failed, whether the robot is moving, and the last acknowledged sequence number;
* ``_send_move(target_deg, speed, seq)``: the target (an exact stop, not blended), the
  speed, then the sequence number that starts it;
* ``_read_joints_deg``: the measured joints (degrees);
* ``_send_stop``: a stop, best effort.

What the contract does with them: ``connect`` opens, refuses a controller that cannot
take a move (one line saying why) and reads the joints once (implausible values — not
finite, beyond ±10 000°, a nonzero magnitude below 1e-20°: a word-order or unit mistake
— are refused). ``move_joints`` checks the target (6 finite angles) and speed (0, 1],
reads the state and refuses as ``connect`` does, waits (up to ``timeout_s``) for the
controller to acknowledge the move this driver last stopped (where it reports the number
requested: a program that has not acted on the stop yet could otherwise end the stopped
move by acknowledging the next move's number), sends the move with a new sequence
number (1..65535, never the controller's last acknowledgement nor the one sent last, so a
restarted driver never repeats what the controller holds), then polls every ``poll_s``
until the controller acknowledges that number and is not moving. A fault during the move
ends it at once; a requested number read back that is not this driver's, or an
acknowledgement of another number, means another client commanded the controller; after
``timeout_s`` the move has failed. On a timeout a stop is sent. Last, the measured joints
must be within 1e-3 rad of the target. Every error is one
:class:`~cellcal.errors.DeviceError` line naming the robot and where it is.
"""

from __future__ import annotations

import logging
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers.base import ROBOT_NAME, DeviceDescription, label
from cellcal.errors import DeviceError, InputError

log = logging.getLogger("cellcal.drivers.robots")

N_JOINTS = 6
POSITION_TOLERANCE_RAD = 1e-3
MAX_JOINT_DEG = 1e4  # beyond this a joint reading is taken for garbage
MIN_NONZERO_DEG = 1e-20  # a word-swapped float32 of a round value lands below this
SEQ_MAX = 0xFFFF


@dataclass(frozen=True)
class ControllerState:
    """One reading of a controller. ``refusal``: why it cannot take a move now (None: it
    can); ``fault``: why a move under way has failed (None: it has not); ``moving``: the
    robot is not yet standing still at its last target; ``ack``: the last acknowledged
    sequence number; ``text``: the reading in a few words, for messages; ``seq``: the
    sequence number the controller holds as requested, where it can be read back (a
    number this driver did not write is another client's), with ``seq_name`` its name."""

    refusal: str | None
    fault: str | None
    moving: bool
    ack: int
    text: str
    seq: int | None = None
    seq_name: str = "the sequence number"


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def checked_target(name: str, q: Array, speed: float) -> Array:
    """The target (rad), after the checks every family makes."""
    target = np.asarray(q, dtype=np.float64)
    if target.shape != (N_JOINTS,) or not np.isfinite(target).all():
        raise InputError(f"{name}: target must be {N_JOINTS} finite joint angles (rad)")
    if (np.abs(np.degrees(target)) > MAX_JOINT_DEG).any():
        raise InputError(f"{name}: target beyond ±{MAX_JOINT_DEG:g} deg")
    if not (math.isfinite(speed) and 0.0 < speed <= 1.0):
        raise InputError(f"{name}: speed must be in (0, 1], got {speed!r}")
    return target


class StopAndMeasureRobot(ABC):
    """``move_joints`` as the contract has it, once for every robot family: the target
    and speed checked, the controller asked whether it can move (``_ready_to_move``),
    the move sent and waited for until the controller says it is done and the robot
    stands still (``_move_and_settle``), the measured joints checked against the target
    (``_check_arrived``). :class:`HandshakeRobot` is the base of the families that
    command a program on their controller; the UR driver implements the three steps with
    ur_rtde's blocking ``moveJ``."""

    name: str

    def move_joints(self, q: Array, speed: float) -> None:
        """Move to ``q`` (rad) at ``speed`` (fraction of maximum); return once the
        controller reports the move done, the robot stands still and its measured joints
        are at the target."""
        target = checked_target(self.name, q, speed)
        self._ready_to_move(target)
        self._move_and_settle(target, speed)
        self._check_arrived(target)

    @abstractmethod
    def _ready_to_move(self, target: Array) -> None:
        """Refuse (one line) a controller that cannot take this move now."""

    @abstractmethod
    def _move_and_settle(self, target: Array, speed: float) -> None:
        """Send the move; return once the controller says it is done and still."""

    @abstractmethod
    def _check_arrived(self, target: Array) -> None:
        """Refuse measured joints that are not at the target."""


class HandshakeRobot(StopAndMeasureRobot):
    """A :class:`~cellcal.drivers.base.Robot` through a controller-side program and a
    sequence handshake; see the module docstring. Subclasses set ``name``, ``where``,
    ``timeout_s`` (a move), ``poll_s`` and ``family`` (the driver's name)."""

    family = ""

    def __init__(self, name: str, where: str, *, timeout_s: float, poll_s: float) -> None:
        for key, value in (("timeout_s", timeout_s), ("poll_s", poll_s)):
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{name}: {key} must be a positive number, got {value!r}")
        self.name = name
        self.where = where
        self.timeout_s = float(timeout_s)
        self.poll_s = float(poll_s)
        self._last_seq: int | None = None
        #: the sequence number of the move last stopped here (see _settled)
        self._stopped_seq: int | None = None
        self._before = ControllerState("not read yet", None, False, 0, "")

    # ------------------------------------------------------------------ the transport

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _state(self) -> ControllerState: ...

    @abstractmethod
    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None: ...

    @abstractmethod
    def _read_joints_deg(self) -> Array: ...

    @abstractmethod
    def _send_stop(self) -> None: ...

    def _watch(self, state: ControllerState, since: ControllerState) -> None:
        """Called at every poll of a move, for what a family checks besides (a
        heartbeat); raise to end the move. Nothing by default."""
        return None

    def _joints_hint(self) -> str:
        """Where a family's implausible joints most likely come from."""
        return "are the controller's units degrees?"

    # ------------------------------------------------------------------ Robot

    def connect(self) -> None:
        """Open the link and refuse a controller that cannot take a move."""
        self._open()
        try:
            state = self._state()
            self._refuse_unless_ready(state, "connect")
            self.actual_joints()
        except DeviceError:
            self._close()
            raise
        log.info("%s: connected to %s (%s)", self.name, self.where, state.text)

    def _ready_to_move(self, target: Array) -> None:
        state = self._state()
        self._refuse_unless_ready(state, "move")
        self._before = self._settled(state)

    def _settled(self, state: ControllerState) -> ControllerState:
        """The state once the controller has acknowledged the move this driver stopped.

        A stopped move stays unacknowledged until the controller's program acts on the
        stop; a program that answers ``ack = seq`` with the number requested *then*
        would acknowledge the next move's number instead, and that move would be taken
        for done without moving. So the next move waits for it, polling, up to
        ``timeout_s``; then it is refused. (A move refused by the controller, a stop
        message, is left to be replaced: this driver sent no stop for it.)"""
        stopped, self._stopped_seq = self._stopped_seq, None
        deadline = time.monotonic() + self.timeout_s
        while stopped is not None and state.seq == stopped and state.ack != stopped:
            if time.monotonic() > deadline:
                raise self._error(
                    f"move refused: the controller has not acknowledged the stopped move "
                    f"({state.seq_name} {stopped}) after {self.timeout_s:g} s ({state.text}); "
                    "is its program running?"
                )
            time.sleep(self.poll_s)
            state = self._state()
            self._refuse_unless_ready(state, "move")
        return state

    def _move_and_settle(self, target: Array, speed: float) -> None:
        before = self._before
        seq = self._next_seq(before.ack)
        self._send_move(np.degrees(target), speed, seq)
        self._last_seq = seq
        self._wait_done(seq, before)

    def _check_arrived(self, target: Array) -> None:
        actual = self.actual_joints()
        err = np.abs(actual - target)
        worst = int(np.argmax(err))
        if err[worst] > POSITION_TOLERANCE_RAD:
            raise self._error(
                f"reports the move done but joint {worst + 1} is at "
                f"{np.degrees(actual[worst]):.4f} deg, target {np.degrees(target[worst]):.4f} "
                f"deg (off by {err[worst]:.2e} rad)"
            )

    def actual_joints(self) -> Array:
        """The measured joint positions (rad)."""
        values = np.asarray(self._read_joints_deg(), dtype=np.float64)
        bad = (
            ~np.isfinite(values)
            | (np.abs(values) > MAX_JOINT_DEG)
            | ((values != 0.0) & (np.abs(values) < MIN_NONZERO_DEG))
        )
        if values.shape != (N_JOINTS,) or bad.any():
            shown = ", ".join(f"{v:.6g}" for v in values.ravel())
            raise self._error(f"implausible actual joints [{shown}] deg; {self._joints_hint()}")
        out: Array = np.radians(values)
        return out

    def describe(self) -> DeviceDescription:
        return DeviceDescription(ROBOT_NAME, self.family, self.where)

    def stop(self) -> None:
        self._stopped_seq = self._last_seq
        self._send_stop()

    def close(self) -> None:
        self._close()

    def __enter__(self) -> HandshakeRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the handshake

    def _refuse_unless_ready(self, state: ControllerState, action: str) -> None:
        if state.refusal is not None:
            raise self._error(f"{action} refused: {state.refusal}")

    def _next_seq(self, ack: int) -> int:
        seq = ack % SEQ_MAX + 1
        if seq == self._last_seq:
            seq = seq % SEQ_MAX + 1
        return seq

    def _wait_done(self, seq: int, before: ControllerState) -> None:
        deadline = time.monotonic() + self.timeout_s
        while True:
            state = self._state()
            self._watch(state, before)
            if state.fault is not None:
                raise self._error(state.fault)
            if state.seq is not None and state.seq != seq:
                raise self._error(
                    f"another client wrote {state.seq_name} = {state.seq} (this driver wrote "
                    f"{seq}): one client at a time"
                )
            if state.ack not in (seq, before.ack):
                raise self._error(
                    f"move interrupted: the controller acknowledged sequence {state.ack}, "
                    f"not {seq} (another command, or another client; {state.text})"
                )
            if state.ack == seq and not state.moving:
                return
            if time.monotonic() > deadline:
                self._stop_quietly()
                raise self._error(
                    f"move not done after {self.timeout_s:g} s (sequence {seq}; {state.text})"
                )
            time.sleep(self.poll_s)

    def _stop_quietly(self) -> None:
        """A stop on the way out of a failed move; its own failure is only logged."""
        self._stopped_seq = self._last_seq
        try:
            self._send_stop()
        except DeviceError as exc:
            log.warning("%s: stop after a failed move failed too: %s", self.name, exc)

    def _error(self, message: str) -> DeviceError:
        return DeviceError(
            one_line(f"{label(self.name, self.where)}: {message}"), device=ROBOT_NAME
        )
