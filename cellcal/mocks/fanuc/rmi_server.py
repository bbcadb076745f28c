"""The FANUC twin: an R-30iB Plus with the Remote Motion Interface, serving the simulated
cell's robot, for the ``fanuc-rmi`` driver, ``cellcal mock fanuc-rmi`` and ``cellcal run
--mock``.

Two TCP servers, as the controller has them: the connection port (16001) answers
``FRC_Connect`` with the session's port (``PortNumber``; 16002 when the twin is served on
16001, as PyPI's ``fanuc-rmi`` client assumes) and keeps nothing open; the session port
takes one client at a time (a second session is closed at once, and ``FRC_Connect``
while one is up answers ErrorID 2556954). Packets are JSON lines (``\\r\\n``).

In the session: commands are answered at once; instructions are checked when they arrive
(RMI running, not in HOLD, the next consecutive ``SequenceID``, speed and termination
valid) — a refused one is answered at once with its ErrorID — and executed one after the
other; an instruction's answer goes out when it has been executed (a joint move: the
robot stopped at the target). The motion is the shared controller model of the KUKA
twins (``mocks/kuka/krc.py``: the cell's limits and speed, its faults): a target beyond
the limits, or the cell's ``robot_protective_stop_every``, stops the robot with an alarm
— ``FRC_SystemFault`` with the instruction's sequence id, RMI in HOLD until
``FRC_Reset``, the alarm's text in ``FRC_ReadError``. ``FRC_Abort`` stops the robot and
ends RMI (``FRC_Initialize`` again). A session that sends nothing for ``idle_s`` (3600 s
at time scale 1, scaled like the motion) gets ``FRC_Terminate`` and is closed.

Faults (:class:`RmiFaults`, settable at run time): the teach pendant enabled
(``TPMode`` 1; the robot does not move), the servo off (``ServoReady`` 0), single step.
Numbers go out as single-precision values printed by Python's ``json``: a real
controller's formatting was not seen.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.drivers import fanuc_rmi_wire as wire
from cellcal.drivers.kuka_kvp_wire import format_axes
from cellcal.mocks.kuka.krc import KrcController, krc_for_cell
from cellcal.mocks.link_server import Link, TcpLinkServer
from cellcal.mocks.twins import FANUC_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.fanuc_rmi import FanucRmiOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.fanuc")

SESSION_PORT = 16002  # the session's port when the twin listens on RMI's 16001
VERSION = (1, 0)  # the twin's own: real controllers' versions were not seen
IDLE_S = 3600.0
CYCLE_S = 0.005  # how often a running instruction is looked at
LIMIT_ALARM = "MOTN-017 Limit error (G:1^A:{axis}) (twin)"
STOP_ALARM = "SRVO-007 External emergency stops (twin)"
SERVO_ALARM = "the servo went off during the move (twin)"
PENDANT_ALARM = "the teach pendant was enabled during the move (twin)"


@dataclass
class RmiFaults:
    tp_enabled: bool = False
    servo_off: bool = False
    single_step: bool = False


@dataclass
class _Instruction:
    name: str
    seq: int
    packet: dict[str, Any]
    krc_seq: int = 0  # the number the KRC loop answers (0: not started)
    until: float = 0.0  # FRC_WaitTime's end (monotonic)


@dataclass
class RmiState:
    running: bool = False
    hold: bool = False
    next_seq: int = 1
    uframe: int = 0
    utool: int = 1
    override: int = 100
    alarms: list[str] = field(default_factory=list)
    queue: deque[_Instruction] = field(default_factory=deque)


class RmiTwin:
    """RMI over a :class:`KrcController`; see the module docstring."""

    def __init__(
        self, controller: KrcController, *, idle_s: float = IDLE_S, time_scale: float = 1.0
    ) -> None:
        self.controller = controller
        self.idle_s = idle_s
        self.time_scale = time_scale
        self.faults = RmiFaults()
        self.state = RmiState()
        self.connect_server = TcpLinkServer(self._connection, name="fanuc-rmi-connect", log=log)
        self.session_server = TcpLinkServer(self._session, name="fanuc-rmi-session", log=log)
        self.session_port = 0
        self._busy = threading.Lock()
        self._krc_seq = 0
        self._started = time.monotonic()
        #: the packets of every session, in order (the last 10 000)
        self.received: deque[dict[str, Any]] = deque(maxlen=10000)

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        """The connection port on ``port`` (0: any free one) and the session's on 16002
        when ``port`` is 16001, else on any free one; returns the connection port."""
        self.session_port = self.session_server.start(
            host, SESSION_PORT if port == wire.PORT else 0
        )[1]
        try:
            return self.connect_server.start(host, port)
        except OSError:
            self.session_server.stop()
            raise

    def stop(self) -> None:
        self.connect_server.stop()
        self.session_server.stop()

    # ------------------------------------------------------------------ the two ports

    def _connection(self, link: Link) -> None:
        for packet in _packets(link):
            if wire.name_of(packet) != ("Communication", "FRC_Connect"):
                _send(link, {**_echo(packet), "ErrorID": 2556941})
                continue
            busy = self._busy.locked()
            _send(
                link,
                {
                    "Communication": "FRC_Connect",
                    "ErrorID": 2556954 if busy else 0,
                    "PortNumber": 0 if busy else self.session_port,
                    "MajorVersion": VERSION[0],
                    "MinorVersion": VERSION[1],
                },
            )

    def _session(self, link: Link) -> None:
        if not self._busy.acquire(blocking=False):
            log.info("fanuc-rmi twin: a second session while one is up: closed")
            return
        try:
            self._serve(link)
        finally:
            with self.controller.lock:
                self.state.running = False
                self.state.queue.clear()
            self._busy.release()

    def _serve(self, link: Link) -> None:
        buffer = b""
        last = time.monotonic()
        idle = self.idle_s * self.time_scale if self.time_scale else self.idle_s
        while not link.stop.is_set():
            for reply in self._advance():
                _send(link, reply)
            if time.monotonic() - last > idle:
                _send(link, {"Communication": "FRC_Terminate"})
                return
            if not link.wait(CYCLE_S):
                continue
            data = link.read()
            if data is None:
                return
            last = time.monotonic()
            try:
                lines, buffer = wire.split_lines(buffer + data)
            except wire.RmiPacketError:
                return  # a client that sends no line ends: closed
            for line in lines:
                try:
                    packet = wire.decode(line)
                except wire.RmiPacketError as exc:
                    log.info("fanuc-rmi twin: %s", exc)
                    _send(link, {"Command": "Unknown", "ErrorID": 2556941})
                    continue
                self.received.append(packet)
                if wire.name_of(packet) == ("Communication", "FRC_Disconnect"):
                    _send(link, {"Communication": "FRC_Disconnect", "ErrorID": 0})
                    return
                answer = self._handle(packet)
                if answer is not None:
                    _send(link, answer)

    # ------------------------------------------------------------------ packets

    def _handle(self, packet: dict[str, Any]) -> dict[str, Any] | None:
        kind, name = wire.name_of(packet)
        with self.controller.lock:
            self.controller.step()
            if kind == "Instruction":
                return self._instruction(name, packet)
            if kind == "Command":
                handler = getattr(self, "_cmd_" + name.removeprefix("FRC_"), None)
                if handler is not None:
                    out: dict[str, Any] = handler(packet)
                    return {"Command": name, "ErrorID": 0, **out}
            return {**_echo(packet), "ErrorID": 2556941}

    def _status_fields(self) -> dict[str, Any]:
        s, f = self.state, self.faults
        return {
            "ServoReady": 0 if f.servo_off or self.controller.stop_message else 1,
            "TPMode": int(f.tp_enabled),
            "RMIMotionStatus": int(s.running),
            "ProgramStatus": 2 if s.running else 0,
            "SingleStepMode": int(f.single_step),
            "NumberUTool": s.utool,
            "NextSequenceID": s.next_seq,
            "NumberUFrame": s.uframe,
            "Override": s.override,
        }

    def _cmd_GetStatus(self, packet: dict[str, Any]) -> dict[str, Any]:
        return self._status_fields()

    def _cmd_Initialize(self, packet: dict[str, Any]) -> dict[str, Any]:
        s, f = self.state, self.faults
        error = 0
        if s.running:
            error = 2556943
        elif f.tp_enabled:
            error = 2556934
        elif f.servo_off or self.controller.stop_message:
            error = 2556935
        elif f.single_step:
            error = 2556971
        if error == 0:
            s.running, s.hold, s.next_seq = True, False, 1
            s.queue.clear()
        return {"ErrorID": error, "GroupMask": packet.get("GroupMask", 1)}

    def _cmd_Abort(self, packet: dict[str, Any]) -> dict[str, Any]:
        if not self.state.running:
            return {"ErrorID": 2556937}
        self._brake()
        self.state.running = False
        return {}

    def _cmd_Reset(self, packet: dict[str, Any]) -> dict[str, Any]:
        self.controller.acknowledge_stop_message()
        self.state.hold = False
        return {}

    def _cmd_ReadError(self, packet: dict[str, Any]) -> dict[str, Any]:
        alarms = self.state.alarms[-5:][::-1] or ["No error (twin)"]
        out: dict[str, Any] = {"Count": len(alarms), "ErrorData": alarms[0]}
        out.update({f"ErrorData{k + 1}": a for k, a in enumerate(alarms) if k})
        return out

    def _cmd_ReadJointAngles(self, packet: dict[str, Any]) -> dict[str, Any]:
        q = [float(np.float32(v)) for v in self.controller.q_now()]
        angles = {j: 0.0 for j in wire.JOINTS}
        angles.update({f"J{k + 1}": v for k, v in enumerate(q)})
        tag = int((time.monotonic() - self._started) * 1000) & 0x7FFFFFFF
        return {"TimeTag": tag, "JointAngle": angles, "Group": packet.get("Group", 1)}

    def _cmd_GetUFrameUTool(self, packet: dict[str, Any]) -> dict[str, Any]:
        s = self.state
        return {"UFrameNumber": s.uframe, "UToolNumber": s.utool, "Group": packet.get("Group", 1)}

    def _cmd_SetUFrameUTool(self, packet: dict[str, Any]) -> dict[str, Any]:
        frame, tool = packet.get("UFrameNumber"), packet.get("UToolNumber")
        if not (isinstance(frame, int) and 0 <= frame <= 9):
            return {"ErrorID": 2556931}
        if not (isinstance(tool, int) and 1 <= tool <= 10):
            return {"ErrorID": 2556930}
        self.state.uframe, self.state.utool = frame, tool
        return {"Group": packet.get("Group", 1)}

    def _cmd_SetOverRide(self, packet: dict[str, Any]) -> dict[str, Any]:
        value = packet.get("Value")
        if not (isinstance(value, int) and 1 <= value <= 100):
            return {"ErrorID": 2556933}
        self.state.override = value
        return {}

    def _instruction(self, name: str, packet: dict[str, Any]) -> dict[str, Any] | None:
        s = self.state
        seq = packet.get("SequenceID")
        error = 0
        if not s.running:
            error = 2556937
        elif s.hold:
            error = 2556952
        elif seq != s.next_seq:
            error = 2556957
        elif name == "FRC_JointMotionJRep":
            error = _joint_motion_error(packet)
        elif name == "FRC_WaitTime":
            t = packet.get("Time")
            error = 0 if isinstance(t, int | float) and 0 <= t <= 3600 else 2556949
        else:
            error = 2556948
        if error:
            return {"Instruction": name, "ErrorID": error, "SequenceID": seq}
        assert isinstance(seq, int)
        s.next_seq += 1
        s.queue.append(_Instruction(name, seq, packet))
        return None

    # ------------------------------------------------------------------ execution

    def _advance(self) -> list[dict[str, Any]]:
        """The answers of instructions done since the last look, and a system fault when
        the robot stopped with an alarm."""
        out: list[dict[str, Any]] = []
        c, s, f = self.controller, self.state, self.faults
        with c.lock:
            c.faults.drives_on = not f.servo_off  # the servo off brakes a move where it is
            c.step()
            while s.queue:
                head = s.queue[0]
                if head.krc_seq == 0 and head.until == 0.0:
                    self._begin(head)
                alarm = self._alarm_text() if c.stop_message else None
                if f.servo_off or f.tp_enabled:
                    alarm = SERVO_ALARM if f.servo_off else PENDANT_ALARM
                if alarm is not None:
                    out.append({"Communication": "FRC_SystemFault", "SequenceID": head.seq})
                    s.alarms.append(alarm)
                    s.hold = True
                    s.queue.clear()
                    c.ack = c.seq  # the instruction is dropped, not taken up again
                    break
                done = (
                    time.monotonic() >= head.until
                    if head.name == "FRC_WaitTime"
                    else c.ack == head.krc_seq and c.move is None
                )
                if not done:
                    break
                s.queue.popleft()
                out.append({"Instruction": head.name, "ErrorID": 0, "SequenceID": head.seq})
        return out

    def _begin(self, ins: _Instruction) -> None:
        c = self.controller
        if ins.name == "FRC_WaitTime":
            ins.until = time.monotonic() + float(ins.packet["Time"]) * self.time_scale
            return
        angles = ins.packet["JointAngle"]
        target = [float(angles[f"J{k + 1}"]) for k in range(len(c.q))]
        pct = max(1, min(100, round(float(ins.packet["Speed"]) * self.state.override / 100)))
        self._krc_seq = self._krc_seq % 0xFFFF + 1
        if self._krc_seq == c.ack:
            self._krc_seq = self._krc_seq % 0xFFFF + 1
        ins.krc_seq = self._krc_seq
        c.write("CC_TARGET", format_axes(target))
        c.write("CC_SPEED", str(pct))
        c.write("CC_SEQ", str(ins.krc_seq))

    def _brake(self) -> None:
        c = self.controller
        if c.move is not None:
            c.write("CC_STOP", "TRUE")
            c.step()
        self.state.queue.clear()

    def _alarm_text(self) -> str:
        lo_hi = self.controller.limits
        target = self.controller.target
        for k, (v, (lo, hi)) in enumerate(zip(target, lo_hi, strict=True)):
            if not lo <= v <= hi:
                return LIMIT_ALARM.format(axis=k + 1)
        return STOP_ALARM


def _joint_motion_error(packet: dict[str, Any]) -> int:
    angles = packet.get("JointAngle")
    if not isinstance(angles, dict) or not all(
        isinstance(angles.get(f"J{k}"), int | float) for k in range(1, 7)
    ):
        return 2556951
    if packet.get("SpeedType") != "Percent":
        return 2556958
    speed = packet.get("Speed")
    if not (isinstance(speed, int | float) and 1 <= speed <= 100):
        return 2556959
    if packet.get("TermType") not in ("FINE", "CNT"):
        return 2556960
    term = packet.get("TermValue", 0)  # PyPI's fanuc-rmi leaves it out of a FINE move
    if not (isinstance(term, int) and 0 <= term <= 100):
        return 2556961
    return 0


def _echo(packet: dict[str, Any]) -> dict[str, Any]:
    kind, name = wire.name_of(packet)
    return {kind: name}


def _packets(link: Link) -> Any:
    """The packets a connection sends, until it closes (bytes that are not RMI end it)."""
    buffer = b""
    while not link.stop.is_set():
        if not link.wait(0.05):
            continue
        data = link.read()
        if data is None:
            return
        try:
            lines, buffer = wire.split_lines(buffer + data)
            packets = [wire.decode(line) for line in lines]
        except wire.RmiPacketError:
            return
        yield from packets


def _send(link: Link, packet: dict[str, Any]) -> None:
    link.write((json.dumps(packet) + "\r\n").encode("ascii"))


def serve(options: FanucRmiOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured FANUC robot on ephemeral ports of a loopback address."""
    twin = RmiTwin(krc_for_cell(options.home_deg, cell, time_scale), time_scale=time_scale)
    host, port = twin.start(FANUC_HOST, 0)
    return RunningTwin(options.model_copy(update={"address": f"{host}:{port}"}), twin)
