"""A robot controller reached over Modbus TCP through a handshake register map
(``docs/robots.md``): KUKA, Fanuc or ABB behind a PLC or gateway,
xArm and Lebai natively. pymodbus 3.16's synchronous ``ModbusTcpClient``.

The handshake, and what the driver does about faults:

* The status registers (heartbeat, status, error code, ack) are read in as few requests
  as their addresses allow: one for each run of consecutive addresses, never across a
  register the map does not have (a controller answers such a read with exception 2),
  the run holding ack first (``ModbusMap.status_reads``).
* ``connect`` reads the status registers and refuses (``DeviceError``) a controller whose
  e-stop or error bit is set or whose remote bit is clear, then reads the actual joints
  and refuses implausible values (not finite, beyond ±10 000°, or a nonzero magnitude
  below 1e-20° — what a word-order mismatch gives).
* ``move_joints`` checks the status again, writes the target joints (deg, float32) and
  the speed, then the command and a new sequence number in ONE write request, and polls
  the status registers every ``poll_s`` until ack == sequence AND in_position AND NOT busy
  (busy clear alone may mean "not started yet"). The error bit or the e-stop end the
  wait at once; a heartbeat that does not change for ``heartbeat_timeout_s`` is a comms
  fault; after ``timeout_s`` the move has failed; an acknowledgement of another sequence
  number (a stop from elsewhere) interrupts it. On a comms fault or a timeout a stop is
  sent (best effort). Finally the actual joints must be within 1e-3 rad of the target.
* Sequence numbers are 1..65535, chosen from the controller's last acknowledgement (and
  never the one this driver sent last), so a restarted driver never repeats the ack
  the controller already holds.
* Every pymodbus exception and every Modbus exception response becomes a one-line
  ``DeviceError`` that names the robot and host:port. After a comms exception the
  socket is dropped (a late reply must not be taken for the next one); the next request
  reconnects.
* ``heartbeat_timeout_s`` is also the timeout of one request: a device that does not
  answer that long is as good as one whose heartbeat stopped.

The options (``[robot]`` with ``driver = "modbus"``) are ``drivers/modbus_options.py``'s,
a module without pymodbus: a configuration is read and planned without it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException

from cellcal.calib.geometry import Array
from cellcal.drivers.base import DeviceContext, DeviceDescription, host_port
from cellcal.drivers.modbus_map import (
    BIT_NAMES,
    BUSY,
    CMD_MOVE_JOINTS,
    CMD_RESET_ERROR,
    CMD_STOP,
    ERROR,
    ESTOP,
    IN_POSITION,
    N_JOINTS,
    READY,
    REMOTE,
    ModbusMap,
)
from cellcal.drivers.modbus_options import ModbusRobotOptions as ModbusRobotOptions
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot
from cellcal.errors import InputError

log = logging.getLogger("cellcal.modbus_robot")
# pymodbus logs through "pymodbus.logging" without a handler, so Python's last-resort
# handler would print e.g. "Connection to (...) failed" on stderr next to our one-line
# error; a NullHandler stops that and leaves the records to the application's logging.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

_F32 = ModbusTcpClient.DATATYPE.FLOAT32
DEFAULT_PORT = 502


@dataclass(frozen=True)
class ModbusRobotStatus:
    """One reading of the status registers."""

    heartbeat: int
    bits: int
    error_code: int
    ack: int

    @property
    def ready(self) -> bool:
        return bool(self.bits & READY)

    @property
    def busy(self) -> bool:
        return bool(self.bits & BUSY)

    @property
    def in_position(self) -> bool:
        return bool(self.bits & IN_POSITION)

    @property
    def error(self) -> bool:
        return bool(self.bits & ERROR)

    @property
    def estop(self) -> bool:
        return bool(self.bits & ESTOP)

    @property
    def remote(self) -> bool:
        return bool(self.bits & REMOTE)

    def describe(self) -> str:
        names = [n for i, n in enumerate(BIT_NAMES) if self.bits & (1 << i)] or ["none"]
        return (
            f"status 0x{self.bits:04x} ({', '.join(names)}), error code {self.error_code}, "
            f"ack {self.ack}"
        )


def _exception_name(code: int) -> str:
    try:
        return ExcCodes(code).name
    except ValueError:
        return "unknown"


class ModbusRobot(HandshakeRobot):
    """A :class:`~cellcal.drivers.base.Robot` behind Modbus TCP; see the module docstring.
    The move → settle → read contract is :class:`HandshakeRobot`'s."""

    family = "modbus"

    def __init__(
        self,
        host: str,
        port: int = 502,
        *,
        name: str = "modbus-robot",
        map: ModbusMap | None = None,
        timeout_s: float = 60.0,
        poll_s: float = 0.01,
        heartbeat_timeout_s: float = 2.0,
    ) -> None:
        if not (math.isfinite(heartbeat_timeout_s) and heartbeat_timeout_s > 0):
            raise InputError(
                f"{name}: heartbeat_timeout_s must be a positive number, "
                f"got {heartbeat_timeout_s!r}"
            )
        if not 0 < port <= 0xFFFF:
            raise InputError(f"{name}: port must be 1..65535, got {port!r}")
        super().__init__(name, f"{host}:{port}", timeout_s=timeout_s, poll_s=poll_s)
        self.host = host
        self.port = port
        self.map = map or ModbusMap()
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self._client = ModbusTcpClient(
            host, port=port, timeout=self.heartbeat_timeout_s, retries=0, name=name
        )
        self._status: ModbusRobotStatus | None = None
        self._heartbeat: tuple[int, float] = (0, 0.0)

    @classmethod
    def from_options(cls, options: ModbusRobotOptions, context: DeviceContext) -> ModbusRobot:
        host, port = host_port(options.address, DEFAULT_PORT)
        return cls(
            host,
            port,
            map=options.map,
            timeout_s=options.move_timeout_s,
            poll_s=options.poll_s,
            heartbeat_timeout_s=options.heartbeat_timeout_s,
        )

    def describe(self) -> DeviceDescription:
        """The controller at host:port: the handshake map has no identity registers (and
        Modbus's device identification, function 43, is not asked: a controller behind a
        PLC or gateway would describe the gateway), so maker, model, firmware and serial
        are None."""
        return super().describe()

    def stop(self) -> None:
        """Command a stop and return once the controller acknowledged it."""
        seq = self._command(CMD_STOP)
        self._wait_ack(seq, "stop")

    # ------------------------------------------------------------------ extras

    def status(self) -> ModbusRobotStatus:
        """Read heartbeat, status bits, error code and acknowledgement: one request for
        each run of consecutive addresses among them (one for the default map), none
        across a register the map does not have (``ModbusMap.status_reads``)."""
        m = self.map
        values: dict[int, int] = {}
        for address, count in m.status_reads():
            regs = self._read(address, count, "status")
            values.update(zip(range(address, address + count), regs, strict=True))
        return ModbusRobotStatus(
            heartbeat=values[m.heartbeat],
            bits=values[m.status],
            error_code=values[m.error_code],
            ack=values[m.ack],
        )

    def actual_pose(self) -> Array:
        """The flange pose the controller reports: x, y, z (mm), a, b, c (rad)."""
        values = self._decode(self._read(self.map.actual_pose, 12, "actual pose"))
        if not np.isfinite(values).all():
            raise self._error("implausible actual pose (not finite)")
        values[3:] = np.radians(values[3:])
        return values

    def reset_error(self) -> None:
        """Command an error reset; DeviceError if the error or the e-stop stays."""
        seq = self._command(CMD_RESET_ERROR)
        status = self._wait_ack(seq, "error reset")
        if status.error or status.estop:
            raise self._error(f"error reset did not clear the fault: {status.describe()}")

    # ------------------------------------------------------------------ the contract's transport

    def _open(self) -> None:
        if not self._client.connect():  # type: ignore[no-untyped-call]
            raise self._error("cannot connect (nothing listening, or unreachable)")

    def _close(self) -> None:
        self._drop()

    def _state(self) -> ControllerState:
        status = self._status = self.status()
        text = status.describe()
        refusal = fault = None
        if status.estop:
            refusal = f"e-stop is set ({text})"
            fault = f"e-stop during the move ({text})"
        elif status.error:
            refusal = f"controller reports error code {status.error_code} ({text})"
            fault = f"move failed: controller reports error code {status.error_code} ({text})"
        elif not status.remote:
            refusal = f"not in remote mode ({text})"
        moving = status.busy or not status.in_position
        return ControllerState(refusal, fault, moving, status.ack, text)

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        m = self.map
        if self._status is not None:
            self._heartbeat = (self._status.heartbeat, time.monotonic())
        self._write(m.target_joints, self._encode(target_deg), "target joints")
        self._write(m.speed, self._encode([speed]), "speed")
        self._write(m.command, [CMD_MOVE_JOINTS, seq], f"command {CMD_MOVE_JOINTS}")

    def _watch(self, state: ControllerState, since: ControllerState) -> None:
        """A heartbeat that does not change for ``heartbeat_timeout_s`` is a comms fault."""
        if self._status is None:
            return
        now = time.monotonic()
        heartbeat, at = self._heartbeat
        if self._status.heartbeat != heartbeat:
            self._heartbeat = (self._status.heartbeat, now)
        elif now - at > self.heartbeat_timeout_s:
            self._stop_quietly()
            raise self._error(
                f"comms fault: heartbeat stuck at {heartbeat} for {now - at:.1f} s during a "
                f"move ({state.text})"
            )

    def _read_joints_deg(self) -> Array:
        return self._decode(self._read(self.map.actual_joints, 2 * N_JOINTS, "actual joints"))

    def _joints_hint(self) -> str:
        return f"is the word order ({self.map.word_order!r}) the controller's?"

    def _send_stop(self) -> None:
        self._command(CMD_STOP)

    # ------------------------------------------------------------------ handshake

    def _command(self, command: int, ack: int | None = None) -> int:
        """Write command and a new sequence number in one request; the sequence number."""
        if ack is None:
            ack = self.status().ack
        seq = self._next_seq(ack)
        self._write(self.map.command, [command, seq], f"command {command}")
        self._last_seq = seq
        return seq

    def _wait_ack(self, seq: int, what: str) -> ModbusRobotStatus:
        deadline = time.monotonic() + min(self.timeout_s, max(self.heartbeat_timeout_s, 1.0))
        while True:
            status = self.status()
            if status.ack == seq:
                return status
            if time.monotonic() > deadline:
                raise self._error(f"{what} not acknowledged (sequence {seq}; {status.describe()})")
            time.sleep(self.poll_s)

    # ------------------------------------------------------------------ registers

    def _drop(self) -> None:
        """Close the socket; the next request reconnects."""
        self._client.close()  # type: ignore[no-untyped-call]

    def _encode(self, values: Array | list[float]) -> list[int]:
        floats = [float(v) for v in values]
        return ModbusTcpClient.convert_to_registers(floats, _F32, word_order=self.map.word_order)

    def _decode(self, registers: list[int]) -> Array:
        values = ModbusTcpClient.convert_from_registers(
            registers, _F32, word_order=self.map.word_order
        )
        # one float32 comes back as a scalar, several as a list
        out: Array = np.atleast_1d(np.asarray(values, dtype=np.float64))
        return out

    def _read(self, address: int, count: int, what: str) -> list[int]:
        span = f"{what} (registers {address}..{address + count - 1})"
        try:
            rr = self._client.read_holding_registers(
                address, count=count, device_id=self.map.device_id
            )
        except (ModbusException, OSError) as exc:
            self._drop()
            raise self._error(f"reading {span} failed: {exc}") from exc
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            raise self._error(
                f"reading {span}: Modbus exception code {code} ({_exception_name(code)})"
            )
        registers = list(rr.registers)
        if len(registers) != count:
            raise self._error(f"reading {span}: {len(registers)} registers in the reply")
        return registers

    def _write(self, address: int, registers: list[int], what: str) -> None:
        span = f"{what} (registers {address}..{address + len(registers) - 1})"
        try:
            rr = self._client.write_registers(address, registers, device_id=self.map.device_id)
        except (ModbusException, OSError) as exc:
            self._drop()
            raise self._error(f"writing {span} failed: {exc}") from exc
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            raise self._error(
                f"writing {span}: Modbus exception code {code} ({_exception_name(code)})"
            )
