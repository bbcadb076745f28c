"""A KUKA robot (KR C4/KR C5, KSS 8 with the EthernetKRL option) through cellcal's
EthernetKRL channel and KRL program.

The controller is the TCP server of the channel (port 54600 by default, as the XML
configuration cellcal ships declares it; one client at a time) and sends a state
telegram every 50 ms (``kuka_eki_wire``); cellcal sends a move with a new sequence
number, or a stop. The move → settle → read contract is
:class:`~cellcal.drivers.stop_and_measure.HandshakeRobot`'s; this module is its
transport. The state telegram gates the moves: the operating mode (``#AUT`` or ``#EX``),
drives, emergency and guard stop, a stop message, the program running; a move is done
when its number is acknowledged, the robot is not in motion and stopped. The joints
read are the telegram's measured axes, from a telegram sent after the acknowledgement.

Faults: nothing listening, a connection the controller closes at once (another client
holds the channel), no telegram within ``request_timeout_s``, a dropped link, and bytes
that are not cellcal's telegrams each end in one line naming the robot; after a link
fault the next request reconnects.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription, host_port
from cellcal.drivers.kuka_eki_wire import (
    EkiState,
    EkiTelegramError,
    format_move,
    format_stop,
    parse_state,
    split_telegrams,
)
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot

log = logging.getLogger("cellcal.drivers.kuka")

DEFAULT_PORT = 54600
UNATTENDED = ("#AUT", "#EX")


class KukaEkiOptions(RobotOptions):
    """``[robot]`` with ``driver = "kuka-eki"``: ``address`` host or host:port (54600);
    a move not acknowledged within ``move_timeout_s`` has failed; no state telegram
    within ``request_timeout_s`` is a fault."""

    driver: Literal["kuka-eki"] = "kuka-eki"
    move_timeout_s: Positive = 60.0
    poll_s: Annotated[float, Field(gt=0, le=1)] = 0.05
    request_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0


class KukaEkiRobot(HandshakeRobot):
    """A KUKA robot through cellcal's EthernetKRL channel; see the module docstring."""

    family = "kuka-eki"

    def __init__(
        self,
        host: str,
        port: int = DEFAULT_PORT,
        *,
        name: str = "kuka-robot",
        options: KukaEkiOptions | None = None,
    ) -> None:
        o = options or KukaEkiOptions()
        super().__init__(name, f"{host}:{port}", timeout_s=o.move_timeout_s, poll_s=o.poll_s)
        self.host, self.port = host, port
        self.request_timeout_s = o.request_timeout_s
        self._sock: socket.socket | None = None
        self._buffer = b""
        self._latest: EkiState | None = None

    @classmethod
    def from_options(cls, options: KukaEkiOptions, context: DeviceContext) -> KukaEkiRobot:
        host, port = host_port(options.address, DEFAULT_PORT)
        return cls(host, port, options=options)

    def describe(self) -> DeviceDescription:
        return DeviceDescription(ROBOT_NAME, self.family, self.where, "KUKA")

    # ------------------------------------------------------------------ the link

    def _open(self) -> None:
        self._close()
        try:
            self._sock = socket.create_connection(
                (self.host, self.port), timeout=self.request_timeout_s
            )
        except ConnectionRefusedError:
            raise self._error(
                "connection refused: is CellCalEki running (its EthernetKRL channel open)?"
            ) from None
        except OSError as exc:
            raise self._error(f"cannot connect ({exc.strerror or exc})") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buffer, self._latest = b"", None
        self._state_telegram()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _send(self, data: bytes) -> None:
        if self._sock is None:
            self._open()
        assert self._sock is not None
        try:
            self._sock.sendall(data)
        except OSError as exc:
            self._close()
            raise self._error(f"link lost ({exc.strerror or exc})") from None

    def _state_telegram(self) -> EkiState:
        """The newest state telegram received in this call: those waiting are read and
        the last one kept; with none waiting, the next one."""
        if self._sock is None:
            self._open()
        sock = self._sock
        assert sock is not None
        deadline = time.monotonic() + self.request_timeout_s
        fresh = False
        while True:
            wait = 0.0 if fresh else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([sock], [], [], wait)
            if not ready:
                if fresh:
                    assert self._latest is not None
                    return self._latest
                self._close()
                raise self._error(
                    f"no state telegram within {self.request_timeout_s:g} s (is CellCalEki "
                    "running, its timer interrupt on?)"
                )
            try:
                data = sock.recv(65536)
            except OSError as exc:
                self._close()
                raise self._error(f"link lost ({exc.strerror or exc})") from None
            if not data:
                self._close()
                first = self._latest is None
                raise self._error(
                    "the controller closed the connection at once: is another client "
                    "connected to the EthernetKRL channel (one at a time)?"
                    if first
                    else "link lost (the controller closed the connection)"
                )
            try:
                telegrams, self._buffer = split_telegrams(self._buffer + data)
                for raw in telegrams:
                    self._latest = parse_state(raw)
            except EkiTelegramError as exc:
                self._close()
                raise self._error(f"not a CellCalEki state telegram: {exc}") from None
            fresh = fresh or bool(telegrams)

    # ------------------------------------------------------------------ the contract's transport

    def _state(self) -> ControllerState:
        s = self._state_telegram()
        text = (
            f"Mode {s.mode}, Drives {int(s.drives)}, EStop {int(s.estop)}, GuardStop "
            f"{int(s.guard_stop)}, StopMess {int(s.stop_message)}, Program {s.program}, "
            f"Seq {s.seq}, Ack {s.ack}, InMotion {int(s.in_motion)}"
        )
        reason = None
        if s.mode not in UNATTENDED:
            reason = (
                f"controller in {s.mode[1:]}: the KRL program runs unattended in AUT or EXT "
                "only (the mode selector on the pendant)"
            )
        elif s.estop:
            reason = "emergency stop: release it and acknowledge on the pendant"
        elif s.guard_stop:
            reason = "guard stop (the cell's safety circuit): close the guard and acknowledge"
        elif not s.drives:
            reason = "drives off: switch them on"
        elif s.stop_message:
            reason = "a stop message is active: acknowledge it on the pendant"
        elif s.program != "#P_ACTIVE":
            reason = f"CellCalEki is not running (Program {s.program}): select it and start it"
        fault = None if reason is None else f"move failed: {reason}"
        moving = s.in_motion or not s.rob_stopped
        return ControllerState(reason, fault, moving, s.ack, text)

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        pct = max(1, min(100, round(speed * 100)))
        self._send(format_move(seq, pct, [float(v) for v in target_deg]))

    def _read_joints_deg(self) -> Array:
        s = self._state_telegram()
        return np.array(s.axes_deg, dtype=np.float64)

    def _send_stop(self) -> None:
        """A stop: the program brakes and abandons the running move (acknowledging it)."""
        self._send(format_stop(self._last_seq or 0))
