"""The Modbus handshake map (``docs/robots.md``): where a robot controller's registers
are, how its float32 words are ordered and which device id answers — one type read
from the cell configuration (``[robot.map]``), used by the driver and served by the
mock twin. The status bits, command codes and error codes of the handshake live here
too, so driver and twin cannot disagree on them.
"""

from __future__ import annotations

import itertools
from typing import Annotated, Literal

from pydantic import Field, model_validator

from cellcal.device_options import Strict

N_JOINTS = 6

# status bits
READY = 1 << 0
BUSY = 1 << 1
IN_POSITION = 1 << 2
ERROR = 1 << 3
ESTOP = 1 << 4
REMOTE = 1 << 5
BIT_NAMES = ("ready", "busy", "in_position", "error", "e-stop", "remote")

# commands
CMD_NONE = 0
CMD_MOVE_JOINTS = 1
CMD_MOVE_LINEAR = 2
CMD_STOP = 3
CMD_RESET_ERROR = 4

# error codes the controller sets with the error bit
ERR_LIMITS = 2
ERR_COMMAND = 3
ERR_PARAMETER = 4

Address = Annotated[int, Field(ge=0, le=0xFFFF)]

#: Every block of the map and its size in registers (float32 = 2 registers).
BLOCKS: dict[str, int] = {
    "heartbeat": 1,
    "status": 1,
    "error_code": 1,
    "ack": 1,
    "actual_joints": 2 * N_JOINTS,
    "actual_pose": 12,
    "target_joints": 2 * N_JOINTS,
    "target_pose": 12,
    "speed": 2,
    "command": 1,
    "sequence": 1,
}
#: The blocks a client writes; the rest are read only.
WRITABLE = ("target_joints", "target_pose", "speed", "command", "sequence")
#: The one-register blocks read at every poll, in the order their requests go out when
#: they lie apart: ack first, so the status bits read after it are never older than the
#: acknowledgement (as in one request), the error code after the status bits.
STATUS_REGISTERS = ("ack", "heartbeat", "status", "error_code")


class ModbusMap(Strict):
    """Holding-register addresses (0-based), the float32 word order and the device id.

    Refused: a block that runs past register 65535, two blocks that overlap, and a
    ``sequence`` that is not the register after ``command`` (both go in one write
    request). Registers between the blocks are holes: the map does not have them, and
    no request touches them (:meth:`status_reads`)."""

    device_id: Annotated[int, Field(ge=0, le=255)] = 1
    word_order: Literal["big", "little"] = "big"
    heartbeat: Address = 0
    status: Address = 1
    error_code: Address = 2
    ack: Address = 3
    actual_joints: Address = 10  # 12 registers: q1..q6, float32, deg
    actual_pose: Address = 30  # 12 registers: x, y, z (mm), a, b, c (deg)
    target_joints: Address = 100  # 12 registers
    target_pose: Address = 112  # 12 registers
    speed: Address = 124  # 2 registers, fraction of maximum
    command: Address = 130
    sequence: Address = 131  # must follow command: both are written in one request

    @model_validator(mode="after")
    def _layout(self) -> ModbusMap:
        spans = sorted((self.span(name), name) for name in BLOCKS)
        for (lo, hi), name in spans:
            if hi > 0xFFFF:
                raise ValueError(f"{name} ({BLOCKS[name]} registers at {lo}) runs past 65535")
        for ((_, hi_a), a), ((lo_b, _), b) in itertools.pairwise(spans):
            if lo_b <= hi_a:
                ra, rb = self.span(a), self.span(b)
                raise ValueError(
                    f"{a} (registers {ra[0]}..{ra[1]}) and {b} (registers {rb[0]}..{rb[1]}) overlap"
                )
        if self.sequence != self.command + 1:
            raise ValueError(
                f"sequence ({self.sequence}) must be the register after command "
                f"({self.command}): both are written in one request"
            )
        return self

    def span(self, block: str) -> tuple[int, int]:
        """First and last register of a block."""
        lo = int(getattr(self, block))
        return lo, lo + BLOCKS[block] - 1

    def status_reads(self) -> tuple[tuple[int, int], ...]:
        """The read requests of one status poll, as (first address, count): the status
        registers (heartbeat, status, error code, ack) in runs of consecutive addresses,
        one request a run, never across a hole; the run holding ``ack`` first, then in
        the order of :data:`STATUS_REGISTERS`. The default map: one request, (0, 4)."""
        runs: list[list[int]] = []
        for address in sorted(int(getattr(self, name)) for name in STATUS_REGISTERS):
            if runs and address == runs[-1][-1] + 1:
                runs[-1].append(address)
            else:
                runs.append([address])
        order = [int(getattr(self, name)) for name in STATUS_REGISTERS]
        runs.sort(key=lambda run: min(order.index(a) for a in run))
        return tuple((run[0], len(run)) for run in runs)
