"""A KUKA robot (KR C4/KR C5, KSS 8) through KUKAVARPROXY and cellcal's KRL loop.

KUKAVARPROXY reads and writes KRL variables over TCP 7000 (``kuka_kvp_wire``). The KRL
loop cellcal ships (``cellcal export robot-program --driver kuka-kvp``, docs/robots.md)
waits until ``CC_SEQ <> CC_ACK``, moves ``PTP CC_TARGET`` with an exact stop at
``CC_SPEED`` % of the axis speeds, stops the advance run, and sets ``CC_ACK = CC_SEQ``;
``CC_STOP = TRUE`` brakes a move and abandons it. The move → settle → read contract is
:class:`~cellcal.drivers.stop_and_measure.HandshakeRobot`'s; this module is its
transport:

* the state, read before and at every poll of a move: ``$MODE_OP`` (the loop runs
  unattended in ``#AUT`` or ``#EX`` only: T1/T2 are refused), ``$PERI_RDY`` (drives on),
  ``$STOPMESS`` (a stop message waiting for acknowledgement), ``$PRO_STATE1`` (the loop
  running: ``#P_ACTIVE``), ``$ROB_STOPPED``, and the loop's ``CC_SEQ``/``CC_ACK``: a
  ``CC_SEQ`` this driver did not write means another client commands the robot;
* a move: ``CC_STOP = FALSE`` (a stale stop cleared), ``CC_TARGET`` (E6AXIS text,
  degrees), ``CC_SPEED`` (1..100), then ``CC_SEQ``;
* the measured joints: ``$AXIS_ACT_MEAS`` (the encoders, not the set-point);
* a stop: ``CC_STOP = TRUE``.

KUKAVARPROXY has no authentication: anyone on the network can move the robot through
it. Keep it on the cell's own network; the driver logs which controller it talks to
(``$ROBNAME[]``, ``$KR_SERIALNO``) at connect, and the campaign records it.

Faults: a refused connection, a reply later than ``request_timeout_s``, a closed link,
bytes that are not a reply, a failed read or write (an unknown variable, a write the
controller refuses) and KRL text that is not what was asked for each end in one line
naming the robot; after a link fault the socket is dropped and the next request
reconnects.
"""

from __future__ import annotations

import logging
import socket
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription, host_port
from cellcal.drivers.kuka_kvp_wire import (
    HEADER,
    MAX_VALUE,
    READ,
    WRITE,
    KrlTextError,
    KvpFrameError,
    decode_reply,
    encode_request,
    format_axes,
    parse_axes,
    parse_bool,
    parse_enum,
    parse_int,
    parse_string,
)
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot
from cellcal.errors import DeviceError

log = logging.getLogger("cellcal.drivers.kuka")

#: a link unused this long (s) is opened afresh: KUKAVARPROXY drops a client idle for 60 s
IDLE_REOPEN_S = 30.0

DEFAULT_PORT = 7000
UNATTENDED = ("#AUT", "#EX")
_VAR = r"^\$?[A-Za-z_][A-Za-z0-9_]*(\[\])?$"


class KukaKvpOptions(RobotOptions):
    """``[robot]`` with ``driver = "kuka-kvp"``: ``address`` host or host:port (7000);
    the loop's variables (``target_var``, ``seq_var``, ``ack_var``, ``speed_var``,
    ``stop_var``) and the measured joints (``joints_var``); a move not acknowledged
    within ``move_timeout_s`` has failed; the state is read every ``poll_s`` while a
    move runs; a reply later than ``request_timeout_s`` is a fault."""

    driver: Literal["kuka-kvp"] = "kuka-kvp"
    target_var: Annotated[str, Field(pattern=_VAR)] = "CC_TARGET"
    seq_var: Annotated[str, Field(pattern=_VAR)] = "CC_SEQ"
    ack_var: Annotated[str, Field(pattern=_VAR)] = "CC_ACK"
    speed_var: Annotated[str, Field(pattern=_VAR)] = "CC_SPEED"
    stop_var: Annotated[str, Field(pattern=_VAR)] = "CC_STOP"
    joints_var: Annotated[str, Field(pattern=_VAR)] = "$AXIS_ACT_MEAS"
    move_timeout_s: Positive = 60.0
    poll_s: Annotated[float, Field(gt=0, le=1)] = 0.05
    request_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    idle_reopen_s: Annotated[float, Field(gt=0, le=3600)] = IDLE_REOPEN_S


class KvpLink:
    """One TCP connection to KUKAVARPROXY: a request, its reply (same msg id). A link
    unused for ``idle_s`` is opened afresh before the next request: the proxy drops a
    client idle for 60 s (its source, ``src/frmMain.frm``: ``tmrHost``), and a request
    sent into such a socket would fail between campaigns."""

    def __init__(
        self, host: str, port: int, timeout_s: float, idle_s: float = IDLE_REOPEN_S
    ) -> None:
        self.host, self.port, self.timeout_s, self.idle_s = host, port, timeout_s, idle_s
        self._sock: socket.socket | None = None
        self._msg_id = 0
        self._used = 0.0

    def open(self) -> None:
        self.close()
        self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._used = time.monotonic()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def request(self, function: int, name: str, value: str | None = None) -> tuple[bool, str]:
        """(ok, value text) of one read or write; OSError or KvpFrameError on a link fault
        (the socket is then closed)."""
        if self._sock is not None and time.monotonic() - self._used > self.idle_s:
            log.info("%s:%d: the link was idle: opened afresh", self.host, self.port)
            self.close()
        if self._sock is None:
            self.open()
        assert self._sock is not None
        self._msg_id = self._msg_id % 0xFFFF + 1
        try:
            self._sock.sendall(encode_request(self._msg_id, function, name, value))
            head = self._exactly(HEADER.size)
            msg_id, length = HEADER.unpack(head)
            if msg_id != self._msg_id or not 6 <= length <= MAX_VALUE + 6:
                raise KvpFrameError(
                    f"received {head.hex(' ')} (message {msg_id}, {length} bytes) while "
                    f"waiting for the reply to message {self._msg_id}"
                )
            reply = decode_reply(msg_id, length, self._exactly(length))
            if reply.function != function:
                raise KvpFrameError(f"reply of function {reply.function} to a {function}")
        except (OSError, KvpFrameError):
            self.close()
            raise
        self._used = time.monotonic()
        return reply.ok, reply.value.decode("ascii", "replace")

    def _exactly(self, n: int) -> bytes:
        assert self._sock is not None
        data = b""
        while len(data) < n:
            chunk = self._sock.recv(n - len(data))
            if not chunk:
                raise ConnectionResetError("the controller closed the connection")
            data += chunk
        return data


class KukaKvpRobot(HandshakeRobot):
    """A KUKA robot through KUKAVARPROXY and the shipped KRL loop; see the module
    docstring."""

    family = "kuka-kvp"

    def __init__(
        self,
        host: str,
        port: int = DEFAULT_PORT,
        *,
        name: str = "kuka-robot",
        options: KukaKvpOptions | None = None,
    ) -> None:
        o = options or KukaKvpOptions()
        super().__init__(name, f"{host}:{port}", timeout_s=o.move_timeout_s, poll_s=o.poll_s)
        self.options = o
        self.link = KvpLink(host, port, o.request_timeout_s, o.idle_reopen_s)
        self.robot_name: str | None = None
        self.serial: str | None = None

    @classmethod
    def from_options(cls, options: KukaKvpOptions, context: DeviceContext) -> KukaKvpRobot:
        host, port = host_port(options.address, DEFAULT_PORT)
        return cls(host, port, options=options)

    def describe(self) -> DeviceDescription:
        return DeviceDescription(
            ROBOT_NAME, self.family, self.where, "KUKA", self.robot_name, None, self.serial
        )

    # ------------------------------------------------------------------ variables

    def read(self, name: str) -> str:
        """The KRL text of a variable; one line if the controller does not give it."""
        ok, value = self._request(READ, name)
        if not ok:
            raise self._error(f"reading {name} failed: no such variable on the controller?")
        return value

    def write(self, name: str, value: str) -> str:
        ok, back = self._request(WRITE, name, value)
        if not ok:
            raise self._error(
                f"writing {name} = {value[:60]} was refused: is the variable declared in "
                "$config.dat (docs/robots.md) and writable?"
            )
        return back

    def _request(self, function: int, name: str, value: str | None = None) -> tuple[bool, str]:
        try:
            return self.link.request(function, name, value)
        except TimeoutError:
            raise self._error(
                f"no reply to {name} within {self.link.timeout_s:g} s (is KUKAVARPROXY running?)"
            ) from None
        except ConnectionRefusedError:
            raise self._error("connection refused: is KUKAVARPROXY running on the KRC?") from None
        except OSError as exc:
            raise self._error(f"link lost ({exc.strerror or exc})") from None
        except KvpFrameError as exc:
            raise self._error(f"not a KUKAVARPROXY reply: {exc}") from None

    # ------------------------------------------------------------------ the contract's transport

    def _open(self) -> None:
        try:
            self.link.open()
        except ConnectionRefusedError:
            raise self._error("connection refused: is KUKAVARPROXY running on the KRC?") from None
        except OSError as exc:
            raise self._error(f"cannot connect ({exc.strerror or exc})") from None
        try:
            self.robot_name = parse_string(self.read("$ROBNAME[]"))
            ok, serial = self._request(READ, "$KR_SERIALNO")  # not every KSS shows it
            self.serial = parse_string(serial) if ok and serial.strip() else None
        except DeviceError:
            self.link.close()
            raise
        log.info(
            "%s: KUKA %s (serial %s) at %s through KUKAVARPROXY (no authentication: keep it "
            "on the cell's own network)",
            self.name,
            self.robot_name,
            self.serial,
            self.where,
        )

    def _close(self) -> None:
        self.link.close()

    def _state(self) -> ControllerState:
        o = self.options
        try:
            mode = parse_enum(self.read("$MODE_OP"), "$MODE_OP")
            drives = parse_bool(self.read("$PERI_RDY"), "$PERI_RDY")
            stop_message = parse_bool(self.read("$STOPMESS"), "$STOPMESS")
            program = parse_enum(self.read("$PRO_STATE1"), "$PRO_STATE1")
            stopped = parse_bool(self.read("$ROB_STOPPED"), "$ROB_STOPPED")
            seq = parse_int(self.read(o.seq_var), o.seq_var)
            ack = parse_int(self.read(o.ack_var), o.ack_var)
        except KrlTextError as exc:
            raise self._error(str(exc)) from None
        text = (
            (
                f"$MODE_OP {mode}, $PERI_RDY {drives}, $STOPMESS {stop_message}, "
                f"$PRO_STATE1 {program}, {o.seq_var} {seq}, {o.ack_var} {ack}"
            )
            .replace("True", "TRUE")
            .replace("False", "FALSE")
        )
        reason = None
        if mode not in UNATTENDED:
            reason = (
                f"controller in {mode[1:]}: the KRL loop runs unattended in AUT or EXT only "
                "(the mode selector on the pendant)"
            )
        elif not drives:
            reason = "drives off ($PERI_RDY FALSE): switch them on"
        elif stop_message:
            reason = "a stop message is active ($STOPMESS): acknowledge it on the pendant"
        elif program != "#P_ACTIVE":
            reason = (
                f"the KRL loop is not running ($PRO_STATE1 {program}): select CellCal and start it"
            )
        fault = None if reason is None else f"move failed: {reason}"
        return ControllerState(reason, fault, not stopped, ack, text, seq, o.seq_var)

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        o = self.options
        # a stop written while the loop stood idle stays TRUE: it would brake this move (or,
        # KRL interrupts firing on the edge, leave the next stop without effect)
        self.write(o.stop_var, "FALSE")
        self.write(o.target_var, format_axes([float(v) for v in target_deg]))
        self.write(o.speed_var, str(max(1, min(100, round(speed * 100)))))
        self.write(o.seq_var, str(seq))

    def _read_joints_deg(self) -> Array:
        name = self.options.joints_var
        try:
            return np.array(parse_axes(self.read(name), name), dtype=np.float64)
        except KrlTextError as exc:
            raise self._error(str(exc)) from None

    def _joints_hint(self) -> str:
        return f"does {self.options.joints_var} hold the axis angles in degrees?"

    def _send_stop(self) -> None:
        self.write(self.options.stop_var, "TRUE")
