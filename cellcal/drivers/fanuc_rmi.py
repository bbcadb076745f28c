"""A FANUC robot (R-30iB Plus and later, with the Remote Motion Interface option R912)
through RMI's JSON lines (``fanuc_rmi_wire``).

The session: a connection to TCP 16001 (``address``), ``FRC_Connect``, whose answer names
the port the session runs on; the driver closes the first connection and opens that
port. There it reads ``FRC_GetStatus`` and refuses a controller whose teach pendant is
enabled or that is in single step (one line saying so), ends a former session's motion
program (``FRC_Abort``), clears alarms (``FRC_Reset``), starts RMI (``FRC_Initialize``
with the configured ``group``'s mask; the controller then expects sequence id 1) and
sets ``uframe``/``utool`` when configured. A controller that refuses any of it is one
line naming its ErrorID and what it means.

A move is one instruction, ``FRC_JointMotionJRep`` (the joints in degrees, ``Percent``
speed, ``FINE`` termination), with the next consecutive ``SequenceID`` (the controller's
``NextSequenceID`` when its status gives one); the controller answers it when the
robot has stopped at the target, and that answer is the move's acknowledgement. Then the
measured joints are read (``FRC_ReadJointAngles``) and must be at the target (the
contract of :class:`~cellcal.drivers.stop_and_measure.HandshakeRobot`, whose connect,
checks and messages this driver shares). A refused instruction is its ErrorID with the
controller's error text (``FRC_ReadError``); an ``FRC_SystemFault`` during the move (an
alarm: a collision, an e-stop, a limit) ends it with the text; no answer within
``move_timeout_s`` aborts the motion (``FRC_Abort``). ``stop()`` aborts too; the next move
initialises again.

The controller ends a session that sent nothing for 60 minutes (``FRC_Terminate``, then
it closes): before its next request the driver opens a new session, which a paused
campaign therefore survives. A link lost during a move, a second client (the
controller's ErrorID 2556954), nothing listening and bytes that are not RMI each end in
one line naming the robot.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import time
from collections import deque
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers import fanuc_rmi_wire as wire
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription, host_port
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot
from cellcal.errors import DeviceError

log = logging.getLogger("cellcal.drivers.fanuc")

BUSY = 2556954  # FRC_Connect's ErrorID while another session is up


class FanucRmiOptions(RobotOptions):
    """``[robot]`` with ``driver = "fanuc-rmi"``: ``address`` host or host:port (16001);
    ``group`` the motion group moved (1..8); ``uframe`` (0..9) and ``utool`` (1..10) set at
    the start of a session when given (else the controller's current ones); a move not
    answered within ``move_timeout_s`` has failed; a command not answered within
    ``request_timeout_s`` is a fault."""

    driver: Literal["fanuc-rmi"] = "fanuc-rmi"
    group: Annotated[int, Field(ge=1, le=8)] = 1
    uframe: Annotated[int, Field(ge=0, le=9)] | None = None
    utool: Annotated[int, Field(ge=1, le=10)] | None = None
    move_timeout_s: Positive = 60.0
    request_timeout_s: Annotated[float, Field(gt=0, le=60)] = 5.0


class FanucRmiRobot(HandshakeRobot):
    """A FANUC robot through the Remote Motion Interface; see the module docstring."""

    family = "fanuc-rmi"

    def __init__(
        self,
        host: str,
        port: int = wire.PORT,
        *,
        name: str = "fanuc-robot",
        options: FanucRmiOptions | None = None,
    ) -> None:
        o = options or FanucRmiOptions()
        super().__init__(name, f"{host}:{port}", timeout_s=o.move_timeout_s, poll_s=0.05)
        self.host, self.port = host, port
        self.options = o
        self.request_timeout_s = o.request_timeout_s
        self._sock: socket.socket | None = None
        self._buffer = b""
        self._inbox: deque[dict[str, Any]] = deque()
        self._fault: int | None = None  # the SequenceID an FRC_SystemFault named (-1: none)
        self._terminated = False
        self._running = False  # RMI initialised in this session and not aborted since
        self._seq = 1
        self._version = ""
        self._controller_next: int | None = None  # NextSequenceID of the last status
        self._controller_running = False  # RMIMotionStatus of the last status

    @classmethod
    def from_options(cls, options: FanucRmiOptions, context: DeviceContext) -> FanucRmiRobot:
        host, port = host_port(options.address, wire.PORT)
        return cls(host, port, options=options)

    def describe(self) -> DeviceDescription:
        return DeviceDescription(
            ROBOT_NAME, self.family, self.where, "FANUC", firmware=self._version or None
        )

    # ------------------------------------------------------------------ the session

    def _open(self) -> None:
        """The handshake on the connection port, the session's port, alarms reset and RMI
        started (unless the controller is in a state that refuses it: ``connect`` says
        why)."""
        self._close_link()
        reply = self._handshake()
        self._check(reply, "connect", read_error=False)
        try:
            port = wire.integer(reply, "PortNumber") if "PortNumber" in reply else 0
            if "MajorVersion" in reply and "MinorVersion" in reply:
                major = wire.integer(reply, "MajorVersion")
                self._version = f"RMI {major}.{wire.integer(reply, 'MinorVersion')}"
        except wire.RmiPacketError as exc:
            raise self._error(f"not RMI: {exc}") from None
        if not 0 < port < 65536:
            raise self._error(f"FRC_Connect named no usable port ({reply.get('PortNumber')!r})")
        self._sock = self._connect_to(port)
        self._buffer, self._inbox, self._fault, self._terminated = b"", deque(), None, False
        self._running = False
        status = self._status()
        if status.tp_enabled or status.single_step:
            return  # connect says why
        if not status.servo_ready:  # an alarm a reset clears (not an e-stop held down)
            self._check(self._call(wire.command("FRC_Reset")), "reset")
            status = self._status()
        if self._refusal(status) is None:
            self._initialise(status)

    def _handshake(self) -> dict[str, Any]:
        """``FRC_Connect``'s answer. "Already connected" is asked again for up to
        ``request_timeout_s``: a session closed a moment ago (this driver's own, before a
        resume) may not be released yet; a session another client holds stays refused."""
        deadline = time.monotonic() + self.request_timeout_s
        while True:
            first = self._connect_to(self.port)
            try:
                first.sendall(wire.encode(wire.connect()))
                reply = self._first_reply(first)
            except OSError as exc:
                raise self._error(f"link lost ({exc.strerror or exc})") from None
            finally:
                first.close()
            if reply.get("ErrorID") != BUSY or time.monotonic() > deadline:
                return reply
            time.sleep(0.1)

    def _connect_to(self, port: int) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, port), timeout=self.request_timeout_s)
        except ConnectionRefusedError:
            raise self._error(
                f"connection to port {port} refused: is the RMI option (R912) installed and "
                "the controller on?"
            ) from None
        except OSError as exc:
            raise self._error(f"cannot connect to port {port} ({exc.strerror or exc})") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def _first_reply(self, sock: socket.socket) -> dict[str, Any]:
        buffer = b""
        deadline = time.monotonic() + self.request_timeout_s
        while True:
            wait = deadline - time.monotonic()
            if wait <= 0 or not select.select([sock], [], [], wait)[0]:
                raise self._error(f"no answer to FRC_Connect within {self.request_timeout_s:g} s")
            try:
                data = sock.recv(4096)
            except OSError as exc:
                raise self._error(f"link lost ({exc.strerror or exc})") from None
            if not data:
                raise self._error("the controller closed the connection before FRC_Connect")
            try:
                lines, buffer = wire.split_lines(buffer + data)
                for line in lines:
                    packet = wire.decode(line)
                    if wire.name_of(packet) == ("Communication", "FRC_Connect"):
                        return packet
            except wire.RmiPacketError as exc:
                raise self._error(f"not RMI: {exc}") from None

    def _initialise(self, status: wire.RmiStatus) -> None:
        """A former session's motion program ended, alarms cleared, RMI started."""
        if status.rmi_running:
            self._call(wire.command("FRC_Abort"))  # its ErrorID: nothing was running
        self._check(self._call(wire.command("FRC_Reset")), "reset")
        mask = 1 << (self.options.group - 1)
        self._check(self._call(wire.command("FRC_Initialize", GroupMask=mask)), "initialise")
        self._running, self._fault, self._seq = True, None, 1
        o = self.options
        if o.uframe is not None or o.utool is not None:
            current = self._call(wire.command("FRC_GetUFrameUTool", Group=o.group))
            self._check(current, "read the frame and tool numbers")
            frame = o.uframe if o.uframe is not None else wire.integer(current, "UFrameNumber")
            tool = o.utool if o.utool is not None else wire.integer(current, "UToolNumber")
            request = wire.command(
                "FRC_SetUFrameUTool", UFrameNumber=frame, UToolNumber=tool, Group=o.group
            )
            self._check(self._call(request), f"set UFrame {frame} and UTool {tool}")
        log.info("%s: RMI initialised (%s)", self.name, self.where)

    def _ensure_session(self) -> None:
        """A new session when the controller ended the last one (FRC_Terminate after 60
        minutes without a packet) or the link is gone."""
        if self._sock is not None:
            with contextlib.suppress(DeviceError):  # the link is gone: a new session below
                self._receive(0.0)
        if self._sock is None or self._terminated:
            log.info("%s: the RMI session ended; opening a new one", self.name)
            self._open()

    def _close(self) -> None:
        """``FRC_Disconnect``, its answer awaited a moment (the controller then frees the
        session for the next client), the link closed."""
        if self._sock is not None and not self._terminated:
            with contextlib.suppress(DeviceError):
                self._call(wire.disconnect(), timeout=min(1.0, self.request_timeout_s))
        self._close_link()

    def _close_link(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._running = False

    # ------------------------------------------------------------------ packets

    def _send(self, packet: dict[str, Any]) -> None:
        if self._sock is None:
            raise self._error("not connected")
        try:
            self._sock.sendall(wire.encode(packet))
        except OSError as exc:
            self._close_link()
            raise self._error(f"link lost ({exc.strerror or exc})") from None

    def _receive(self, timeout: float) -> None:
        """What arrived within ``timeout``: answers into the inbox; a system fault and
        the session's end noted."""
        sock = self._sock
        if sock is None:
            raise self._error("not connected")
        if not select.select([sock], [], [], max(0.0, timeout))[0]:
            return
        try:
            data = sock.recv(65536)
        except OSError as exc:
            self._close_link()
            raise self._error(f"link lost ({exc.strerror or exc})") from None
        if not data:
            ended = self._terminated
            self._close_link()
            raise self._error(
                "the controller ended the RMI session (FRC_Terminate: 60 minutes without a packet)"
                if ended
                else "link lost (the controller closed the connection)"
            )
        try:
            lines, self._buffer = wire.split_lines(self._buffer + data)
            packets = [wire.decode(line) for line in lines]
        except wire.RmiPacketError as exc:
            self._close_link()
            raise self._error(f"not RMI: {exc}") from None
        for packet in packets:
            name = wire.name_of(packet)
            if name == ("Communication", "FRC_SystemFault"):
                seq = packet.get("SequenceID")
                self._fault = seq if isinstance(seq, int) and not isinstance(seq, bool) else -1
                log.warning("%s: FRC_SystemFault (sequence %s)", self.name, seq)
            elif name == ("Communication", "FRC_Terminate"):
                self._terminated = True
            else:
                self._inbox.append(packet)

    def _call(
        self, packet: dict[str, Any], timeout: float | None = None, seq: int | None = None
    ) -> dict[str, Any]:
        """Send ``packet`` and wait for its answer (an instruction's: the one with its
        sequence id). A system fault while an instruction waits ends the wait; no answer
        in time is a fault (for an instruction, after an abort)."""
        want = wire.name_of(packet)
        wait = timeout or self.request_timeout_s
        self._send(packet)
        deadline = time.monotonic() + wait
        while True:
            while self._inbox:
                reply = self._inbox.popleft()
                if wire.name_of(reply) == want and (seq is None or reply.get("SequenceID") == seq):
                    return reply
                log.info("%s: an answer nobody waits for dropped: %s", self.name, reply)
            if seq is not None and self._fault is not None:
                raise self._system_fault(seq)
            if self._terminated:
                self._close_link()
                raise self._error(f"the controller ended the RMI session during {want[1]}")
            left = deadline - time.monotonic()
            if left <= 0:
                if seq is None:
                    raise self._error(f"no answer to {want[1]} within {wait:g} s")
                self._stop_quietly()
                raise self._error(f"move not done after {wait:g} s (sequence {seq})")
            self._receive(left)

    def _check(self, reply: dict[str, Any], action: str, *, read_error: bool = True) -> None:
        try:
            error_id = wire.integer(reply, "ErrorID")
        except wire.RmiPacketError as exc:
            raise self._error(f"not RMI: {exc}") from None
        if error_id == 0:
            return
        detail = self._error_texts() if read_error else ""
        raise self._error(
            f"{action} refused: {wire.error_text(error_id)}" + (f": {detail}" if detail else "")
        )

    def _error_texts(self) -> str:
        """The controller's error texts, best effort (they only explain an ErrorID)."""
        try:
            return wire.errors_of(self._call(wire.command("FRC_ReadError", Count=1)))
        except DeviceError:
            return ""

    def _system_fault(self, seq: int) -> DeviceError:
        self._running = False
        detail = self._error_texts()
        return self._error(
            f"system fault during the move (sequence {seq}): "
            f"{detail or 'the controller gave no error text'}; reset the alarm, then resume"
        )

    def _status(self) -> wire.RmiStatus:
        reply = self._call(wire.command("FRC_GetStatus"))
        self._check(reply, "status", read_error=False)
        try:
            return wire.status_of(reply)
        except wire.RmiPacketError as exc:
            raise self._error(str(exc)) from None

    @staticmethod
    def _refusal(status: wire.RmiStatus) -> str | None:
        if status.tp_enabled:
            return "the teach pendant is enabled: disable it (RMI moves the robot in AUTO only)"
        if status.single_step:
            return "the controller is in single step mode: switch it off"
        if not status.servo_ready:
            return "the servo is not ready (an alarm, or an e-stop): reset it on the pendant"
        return None

    # ------------------------------------------------------------------ the contract

    def _state(self) -> ControllerState:
        self._ensure_session()
        status = self._status()
        self._controller_next = status.next_sequence
        self._controller_running = status.rmi_running
        return ControllerState(self._refusal(status), None, False, 0, status.text)

    def _ready_to_move(self, target: Array) -> None:
        super()._ready_to_move(target)
        if not (self._running and self._controller_running):
            self._initialise(self._status())
        elif self._controller_next is not None and self._controller_next != self._seq:
            log.info(
                "%s: the controller expects sequence %d, not %d: taken",
                self.name,
                self._controller_next,
                self._seq,
            )
            self._seq = self._controller_next

    def _move_and_settle(self, target: Array, speed: float) -> None:
        seq = self._seq
        self._send_move(np.degrees(target), speed, seq)

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        pct = max(1, min(100, round(speed * 100)))
        packet = wire.joint_motion(seq, [float(v) for v in target_deg], pct)
        reply = self._call(packet, timeout=self.timeout_s, seq=seq)
        self._check(reply, f"move (sequence {seq})")
        self._last_seq, self._seq = seq, seq + 1

    def _read_joints_deg(self) -> Array:
        self._ensure_session()
        reply = self._call(wire.command("FRC_ReadJointAngles", Group=self.options.group))
        self._check(reply, "read the joint angles")
        try:
            return np.array(wire.joints_of(reply, 6), dtype=np.float64)
        except wire.RmiPacketError as exc:
            raise self._error(str(exc)) from None

    def _send_stop(self) -> None:
        """``FRC_Abort``: the motion program ends, the robot stops; the next move
        initialises again."""
        if self._sock is None:
            return
        self._ensure_session()  # a session the controller ended: a new one to abort in
        self._running = False
        self._call(wire.command("FRC_Abort"))
