"""The robot controller behind the Modbus twin: its registers, status, commands, faults
and motion, with the handshake register map of ``docs/robots.md`` — no sockets (the
server, ``mocks/modbus/server.py``, decodes the requests and hands them here).

The float32 registers are encoded with :mod:`struct` (``mbap.floats_to_registers``),
independently of any client's converters, so a driver that gets the word order wrong is
caught.

Registers (holding, 0-based; function codes 3 and 4 read the same ones; float32 in the
configured word order): exactly those of the configured map (``ModbusMap``), as a
controller has them. Reading or writing any other address — a hole between two blocks
included, and a range that covers one — answers exception code 2, writing a read-only
block too, and nothing of such a request is done. The default map's:

* 0 heartbeat, 1 status, 2 error code, 3 acknowledged sequence — read only;
* 10..21 actual joints (deg), 30..41 actual flange pose (mm, deg) — read only;
* 100..111 target joints (deg), 112..123 target pose, 124..125 speed (0..1),
  130 command, 131 sequence — read/write.

Behaviour (the spec leaves room; these fill it):

* Status bits: 0 ready (no error, no e-stop), 1 busy, 2 in_position, 3 error, 4 e-stop,
  5 remote (set unless the ``local`` fault is on).
* The heartbeat counts the controller's 10 ms cycles since it started (wall time, not
  requests), unless the ``stale_heartbeat`` fault is on. Every read also advances the
  simulation first.
* A command is a write request that covers 130 *and* 131 (function 16, or the write of
  23, which is done before its read). With a sequence number other than the last
  acknowledged one it is accepted (ack = sequence); a write of one of the two alone, or
  a repeated sequence number, is stored and otherwise ignored.
* Command 1 (move joints) with the target joints and speed already written: the move
  starts at once (busy, not in position), or after ``start_delay_reads`` reads during
  which it is accepted but not started (not busy, not in position). It is the shared
  motion model's constant-speed move (:class:`~cellcal.mocks.motion.JointMove`, in
  degrees, at ``joint_speed_deg_s × speed``): it lasts ``travel / (joint_speed_deg_s ×
  speed) × time_scale`` wall seconds, travel being the largest joint travel (deg), the
  joints interpolated in between. It is in position (not busy) when the robot arrives,
  whoever reads or not; with ``time_scale`` 0 it arrives at once.
* Refusals set the error bit and the error code: 2 target outside the limits (or not
  finite), 3 unsupported command (2 move linear and unknown codes), 4 speed not in
  [0.001, 1]. While the error or the e-stop bit is set, or in local mode, moves are
  acknowledged and not executed. Command 3 stops a move where it is (not in position);
  command 4 clears the error and the e-stop bits; command 0 only acknowledges.
* Faults (:class:`ModbusRobotFaults`, settable at run time) act when a move is
  commanded, except ``no_ack`` (no command is acknowledged or executed),
  ``stale_heartbeat`` and ``local`` (remote bit clear).
* ``on_move(q_rad)`` and ``pose_fn(q_rad)`` run in the serving thread at a read, when
  the joints have changed; an exception from them answers exception code 4 (device
  failure). Requests are served one at a time, callbacks included, whatever the
  connection.
* :attr:`~ModbusRobotController.requests` records every request served (not those
  answered with an exception): a write with its values, a read with the status and ack
  it answered when it covered them; function 23 records its write, then its read.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cellcal.drivers.modbus_map import (
    BLOCKS,
    BUSY,
    CMD_MOVE_JOINTS,
    CMD_NONE,
    CMD_STOP,
    ERR_COMMAND,
    ERR_LIMITS,
    ERR_PARAMETER,
    ERROR,
    ESTOP,
    IN_POSITION,
    N_JOINTS,
    READY,
    REMOTE,
    WRITABLE,
    ModbusMap,
)
from cellcal.drivers.modbus_map import CMD_RESET_ERROR as CMD_RESET
from cellcal.mocks.modbus.mbap import (
    DEVICE_FAILURE,
    ILLEGAL_ADDRESS,
    ModbusError,
    Request,
    floats_to_registers,
    registers_to_floats,
)
from cellcal.mocks.motion import JointMove

log = logging.getLogger("cellcal.mocks.modbus_robot")

MIN_SPEED = 0.001
HEARTBEAT_PERIOD_S = 0.01
_N_REGISTERS = 0x10000
_UNMAPPED, _READ_ONLY, _READ_WRITE = 0, 1, 2


@dataclass(frozen=True)
class ModbusRobotFaults:
    """Fault injection; everything off by default."""

    no_ack: bool = False  # never acknowledge (nor execute) commands
    error_code: int | None = None  # set the error bit with this code when a move is commanded
    estop: bool = False  # e-stop bit set when a move is commanded
    stale_heartbeat: bool = False  # heartbeat stops incrementing
    start_delay_reads: int = 0  # reads during which a move is accepted but not started
    local: bool = False  # remote bit clear (local mode): moves acknowledged, not executed
    estop_every: int = 0  # every N-th move command ends in a protective stop (0: never)

    def __post_init__(self) -> None:
        if self.error_code is not None and not 1 <= self.error_code <= 0xFFFF:
            raise ValueError(
                f"ModbusRobotFaults.error_code must be 1..65535, got {self.error_code}"
            )
        if self.start_delay_reads < 0:
            raise ValueError(
                f"ModbusRobotFaults.start_delay_reads must be >= 0, got {self.start_delay_reads}"
            )


@dataclass(frozen=True)
class ModbusRequest:
    """One request as the device saw it: ``values`` for writes; ``status`` and ``ack``
    as answered, for reads that covered those registers."""

    function_code: int
    address: int
    count: int
    values: tuple[int, ...] | None
    status: int | None = None
    ack: int | None = None


@dataclass
class _Move:
    path: JointMove  # degrees, seconds of robot time
    pending_reads: int
    started_at: float | None  # wall time (monotonic)


def _to_float32(values: np.ndarray) -> np.ndarray:
    """Values as a float32 register would hold them (overflow → inf)."""
    with np.errstate(over="ignore"):
        out: np.ndarray = values.astype(np.float32).astype(np.float64)
    return out


class ModbusRobotController:
    """A robot controller's Modbus registers and behaviour; see the module docstring."""

    def __init__(
        self,
        *,
        q0_deg: np.ndarray | list[float] | tuple[float, ...],
        limits_deg: list[tuple[float, float]] | None = None,
        joint_speed_deg_s: float = 60.0,
        time_scale: float = 0.0,
        map: ModbusMap | None = None,
        faults: ModbusRobotFaults = ModbusRobotFaults(),
        on_move: Callable[[np.ndarray], None] | None = None,
        pose_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        q0 = np.asarray(q0_deg, dtype=np.float64)
        if q0.shape != (N_JOINTS,) or not np.isfinite(q0).all():
            raise ValueError(f"q0_deg must be {N_JOINTS} finite values, got {q0_deg!r}")
        if limits_deg is not None:
            lim = np.asarray(limits_deg, dtype=np.float64)
            if lim.shape != (N_JOINTS, 2) or not (lim[:, 0] < lim[:, 1]).all():
                raise ValueError(f"limits_deg must be {N_JOINTS} (low, high) pairs, low < high")
            self._limits: np.ndarray | None = lim
        else:
            self._limits = None
        if not (math.isfinite(joint_speed_deg_s) and joint_speed_deg_s > 0):
            raise ValueError(f"joint_speed_deg_s must be > 0, got {joint_speed_deg_s}")
        if not (math.isfinite(time_scale) and time_scale >= 0):
            raise ValueError(f"time_scale must be >= 0, got {time_scale}")
        self.joint_speed_deg_s = float(joint_speed_deg_s)
        self.time_scale = float(time_scale)
        self.map = map or ModbusMap()
        self.word_order = self.map.word_order
        self.device_id = self.map.device_id
        self.faults = faults
        self.on_move = on_move
        self.pose_fn = pose_fn

        self._registers = [0] * _N_REGISTERS
        self._moves_commanded = 0
        self._access = bytearray(_N_REGISTERS)
        for name, size in BLOCKS.items():
            lo, hi = self.map.span(name)
            kind = _READ_WRITE if name in WRITABLE else _READ_ONLY
            self._access[lo : hi + 1] = bytes([kind]) * size
        self._serial = threading.Lock()  # one request at a time, callbacks included
        self._lock = threading.Lock()  # the state, for inspection from other threads
        self._q = _to_float32(q0)
        self._pose = np.zeros(6)
        self._pose_stale = True
        self._heartbeat = 0
        self._started = time.monotonic()
        self._ack = 0
        self._error_code = 0
        self._estop = False
        self._in_position = True
        self._motion: _Move | None = None
        self._moved: np.ndarray | None = None  # joints changed since on_move last ran
        self._requests: list[ModbusRequest] = []

    # ------------------------------------------------------------------ inspection

    @property
    def q_deg(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def requests(self) -> list[ModbusRequest]:
        """Every request the device has served (copy), oldest first."""
        with self._lock:
            return list(self._requests)

    def clear_requests(self) -> None:
        with self._lock:
            self._requests.clear()

    # ------------------------------------------------------------------ requests

    def serve(self, request: Request) -> list[int]:
        """Serve one decoded request: its write, then its read; returns the registers
        read. ``ModbusError`` with the exception code to answer, nothing done then."""
        with self._serial:
            if request.values:
                self._check(request.write_address, len(request.values), _READ_WRITE)
            if request.read_count:
                self._check(request.read_address, request.read_count, _READ_ONLY)
            if request.values:
                with self._lock:
                    self._write(request.function, request.write_address, request.values)
            if not request.read_count:
                return []
            return self._read(request.function, request.read_address, request.read_count)

    def _check(self, address: int, count: int, access: int) -> None:
        end = address + count
        if end > _N_REGISTERS or min(self._access[address:end]) < access:
            what = "write" if access == _READ_WRITE else "read"
            raise ModbusError(ILLEGAL_ADDRESS, f"{what} of {count} registers at {address}")

    def _write(self, function: int, address: int, values: tuple[int, ...]) -> None:
        self._requests.append(ModbusRequest(function, address, len(values), values))
        self._registers[address : address + len(values)] = values
        m = self.map
        if address <= m.command and m.sequence < address + len(values):
            self._command(values[m.command - address], values[m.sequence - address])

    def _read(self, function: int, address: int, count: int) -> list[int]:
        now = time.monotonic()
        with self._lock:
            if not self.faults.stale_heartbeat:
                self._heartbeat = int((now - self._started) / HEARTBEAT_PERIOD_S) & 0xFFFF
            self._advance(now)
            moved, self._moved = self._moved, None
            q = self._q.copy()
            on_move, pose_fn, pose_stale = self.on_move, self.pose_fn, self._pose_stale
        pose: np.ndarray | None = None
        try:
            if moved is not None and on_move is not None:
                on_move(np.radians(moved))
            if pose_stale and pose_fn is not None:
                pose = np.asarray(pose_fn(np.radians(q)), dtype=np.float64)
        except Exception as exc:
            log.exception("Modbus robot twin: on_move or pose_fn failed")
            raise ModbusError(DEVICE_FAILURE, "on_move or pose_fn failed") from exc
        with self._lock:
            if pose is not None:
                if pose.shape != (6,):
                    log.error("Modbus robot twin: pose_fn returned shape %s", pose.shape)
                    raise ModbusError(DEVICE_FAILURE, f"pose_fn returned shape {pose.shape}")
                self._pose = pose
                self._pose_stale = False
            status = self._publish()
            covers = range(address, address + count)
            seen = status if self.map.status in covers else None
            ack = self._ack if self.map.ack in covers else None
            self._requests.append(ModbusRequest(function, address, count, None, seen, ack))
            return self._registers[address : address + count]

    # ------------------------------------------------------------------ controller

    def _command(self, command: int, sequence: int) -> None:
        if self.faults.no_ack or sequence == self._ack:
            return
        self._ack = sequence
        if command == CMD_NONE:
            return
        if command == CMD_STOP:
            if self._motion is not None:
                self._advance(time.monotonic(), finish=False)
                self._motion = None
                self._in_position = False
            return
        if command == CMD_RESET:
            self._error_code = 0
            self._estop = False
            return
        if command != CMD_MOVE_JOINTS:
            self._fail(ERR_COMMAND)
            return
        faults = self.faults
        self._moves_commanded += 1
        if faults.estop or (faults.estop_every and self._moves_commanded % faults.estop_every == 0):
            self._estop = True
            self._halt()
            return
        if faults.error_code is not None:
            self._fail(faults.error_code)
            return
        if self._estop or self._error_code or faults.local:
            return
        m = self.map
        target = registers_to_floats(
            self._registers[m.target_joints : m.target_joints + 2 * N_JOINTS], self.word_order
        )
        speed = float(
            registers_to_floats(self._registers[m.speed : m.speed + 2], self.word_order)[0]
        )
        if not np.isfinite(target).all() or (
            self._limits is not None
            and ((target < self._limits[:, 0]) | (target > self._limits[:, 1])).any()
        ):
            self._fail(ERR_LIMITS)
            return
        if not (MIN_SPEED <= speed <= 1.0):  # NaN fails too
            self._fail(ERR_PARAMETER)
            return
        pending = faults.start_delay_reads
        self._motion = _Move(
            path=JointMove(self._q.copy(), target, v=self.joint_speed_deg_s * speed),
            pending_reads=pending,
            started_at=time.monotonic() if pending == 0 else None,
        )
        self._in_position = False

    def _fail(self, code: int) -> None:
        self._error_code = code
        self._halt()

    def _halt(self) -> None:
        if self._motion is not None:
            self._advance(time.monotonic(), finish=False)
            self._motion = None
        self._in_position = False

    def _advance(self, now: float, *, finish: bool = True) -> None:
        """Move the joints to where the motion has them at ``now``."""
        m = self._motion
        if m is None:
            return
        if m.started_at is None:
            if m.pending_reads > 0:
                m.pending_reads -= 1
                return
            m.started_at = now
        # robot time: wall time / time_scale; time_scale 0 arrives at once
        t = (now - m.started_at) / self.time_scale if self.time_scale > 0 else math.inf
        q = _to_float32(m.path.at(t)[0])
        if finish and m.path.done(t):
            self._motion = None
            self._in_position = True
        if not np.array_equal(q, self._q):
            self._q = q
            self._moved = q.copy()
            self._pose_stale = True

    def _status(self) -> int:
        status = 0 if self.faults.local else REMOTE
        if self._error_code:
            status |= ERROR
        if self._estop:
            status |= ESTOP
        if not (self._error_code or self._estop):
            status |= READY
        if self._motion is not None and self._motion.started_at is not None:
            status |= BUSY
        if self._in_position:
            status |= IN_POSITION
        return status

    def _publish(self) -> int:
        """Write the controller's state into its read-only registers; the status."""
        status = self._status()
        m, regs = self.map, self._registers
        regs[m.heartbeat] = self._heartbeat
        regs[m.status] = status
        regs[m.error_code] = self._error_code
        regs[m.ack] = self._ack
        j, p = m.actual_joints, m.actual_pose
        regs[j : j + 2 * N_JOINTS] = floats_to_registers(self._q, self.word_order)
        regs[p : p + 12] = floats_to_registers(self._pose, self.word_order)
        return status
