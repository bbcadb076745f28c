"""The UR twin's real-time client interface (TCP 30003): URScript in, robot state out.
Stdlib only.

In: lines of URScript. A program ``def name(): ... end`` (or ``sec``) is run when its
``end`` arrives: ``rtde_control`` starts ur_rtde's control loop (see
:mod:`cellcal.mocks.ur.controller`); other programs run without effect. Lines outside a
program are logged and ignored.

Out: every controller cycle (500 Hz) the real-time state packet of the 5.10+ layout
("RealTime 5.10" of UR's client interfaces), 1220 bytes: the message size (int32),
then 152 big-endian doubles. Columns are UR's gnuplot columns (1-based, after the size):

=========  ==========================================
1          time (controller cycles × 2 ms)
2-31       q, qd, qdd, I, M target
32-55      q, qd, I actual; I control
56-67      tool vector actual (m, rotation vector), TCP speed actual
68-85      TCP force; tool vector target, TCP speed target
86-92      digital input bits, motor temperatures
93-95      controller timer, test value (0), robot mode
96-102     joint modes, safety mode
103-117    UR internal (0) ×6, tool accelerometer, UR internal (0) ×6
118-121    speed scaling, linear momentum norm, UR internal (0) ×2
122-130    V main, V robot, I robot, V actual (joints)
131-132    digital outputs, program state (the runtime state)
133-139    elbow position, elbow velocity, safety status
140-152    UR internal (0) ×3, payload mass, CoG, inertia
=========  ==========================================

A client that does not read never blocks the controller: a packet that finds the
previous one still unsent is dropped, as the controller drops what it cannot send.
"""

from __future__ import annotations

import logging
import re
import struct
from typing import TYPE_CHECKING

from cellcal.mocks.ur import fields as f
from cellcal.mocks.ur.rtde_codec import CYCLE_S

if TYPE_CHECKING:
    from cellcal.mocks.ur.controller import Controller

log = logging.getLogger("cellcal.mocks.ur")

SCRIPT_PORT = 30003
REALTIME_DOUBLES = 152
REALTIME_SIZE = 4 + 8 * REALTIME_DOUBLES  # 1220
_PACKET = struct.Struct(f">i{REALTIME_DOUBLES}d")
#: the longest script line kept, bytes (a longer one is dropped as it comes)
MAX_LINE = 65536
#: the longest program kept without its ``end``, bytes (ur_rtde's control script: ~60 KB)
MAX_PROGRAM = 4 * 1024 * 1024
_PROGRAM_START = re.compile(r"(def|sec)\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(\s*\)\s*:")


def realtime_packet(c: Controller) -> bytes:
    """The cycle's real-time state packet (see the module docstring)."""
    joint_mode = float(f.JOINT_MODE_BY_ROBOT_MODE.get(c.robot_mode, 253))
    sixes = [
        c.q_pub,
        c.qd_pub,
        c.qdd_pub,
        f.CURRENTS,
        f.MOMENTS,
        c.q_pub,
        c.qd_pub,
        f.CURRENTS,
        f.CONTROL_OUTPUT,
        c.tcp,
        c.tcp_speed,
        f.TCP_FORCE,
        c.tcp,
        c.tcp_speed,
    ]
    values: list[float] = [c.cycle * CYCLE_S]
    for six in sixes:
        values.extend(six)
    values.append(0.0)  # digital input bits
    values.extend(f.TEMPERATURES)
    values += [0.35, 0.0, float(c.robot_mode)]
    values += [joint_mode] * 6
    values.append(float(c.safety_mode()))
    values += [0.0] * 6
    values.extend(f.ACCELEROMETER)
    values += [0.0] * 6
    values += [1.0, 0.0, 0.0, 0.0]  # speed scaling, momentum, UR internal
    powered = c.robot_mode != 3
    values += [48.1, 47.9 if powered else 0.0, 0.92 if powered else 0.0]
    values.extend(f.JOINT_VOLTAGE if powered else [0.0] * 6)
    values += [float(c.digital_outputs), float(c.runtime_state)]
    values.extend(f.ELBOW)
    values += [0.0] * 3
    values.append(float(c.safety_mode()))
    values += [0.0] * 3
    values.append(c.payload)
    values.extend(f.PAYLOAD_COG)
    values += [0.0] * 6
    return _PACKET.pack(REALTIME_SIZE, *values)


class ScriptReader:
    """The URScript arriving on one connection, line by line; bounded: a line longer
    than :data:`MAX_LINE` bytes is dropped as it comes, a program longer than
    :data:`MAX_PROGRAM` bytes without its ``end`` is dropped, each said in a log line."""

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.buf = bytearray()
        self.dropping = False  # the rest of an overlong line
        self.program: list[str] | None = None
        self.size = 0  # bytes of the program so far
        self.name = ""

    def feed(self, data: bytes) -> None:
        self.buf += data
        start = 0
        while (nl := self.buf.find(b"\n", start)) >= 0:
            raw = bytes(self.buf[start:nl])
            start = nl + 1
            if self.dropping:
                self.dropping = False
                continue
            self._line(raw.decode("utf-8", "replace").rstrip("\r"))
        del self.buf[:start]
        if len(self.buf) > MAX_LINE:
            if not self.dropping:
                log.warning(
                    "UR twin %s: a script line longer than %d bytes: dropped",
                    self.ctl.host,
                    MAX_LINE,
                )
            self.dropping = True
            self.buf.clear()

    def _line(self, line: str) -> None:
        if self.program is not None:
            self.size += len(line) + 1
            if self.size > MAX_PROGRAM:
                log.warning(
                    "UR twin %s: program %r longer than %d bytes and no end: an endless "
                    "program, dropped",
                    self.ctl.host,
                    self.name,
                    MAX_PROGRAM,
                )
                self.program = None
        if self.program is None:
            m = _PROGRAM_START.match(line)
            if m is not None:
                self.program = [line]
                self.size = len(line) + 1
                self.name = m.group(2) if m.group(1) == "def" else ""
            elif line.strip():
                log.info("UR twin %s: script line ignored: %.80s", self.ctl.host, line)
            return
        self.program.append(line)
        if line == "end":
            text = "\n".join(self.program) + "\n"
            name = self.name
            self.program = None
            if name:
                log.debug("UR twin %s: program %r (%d bytes)", self.ctl.host, name, len(text))
                self.ctl.run_script(name, text)
