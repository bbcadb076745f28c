"""A Yaskawa Motoman robot (DX100, DX200, FS100, YRC1000, YRC1000micro) through the
controller's High-Speed Ethernet Server (UDP 10040; ``yaskawa_hses_wire``).

Nothing of cellcal's runs on the controller. ``connect`` reads the status (0x72) and
refuses a controller in TEACH or without command remote (one line saying so); otherwise
it resets an alarm and cancels an error (0x82), releases a hold cellcal set (0x83) and
turns the servo on (0x83), waiting until the status says it is on. A move is the
joint-pulse move (0x8B, link absolute at ``speed`` × 100 % in 0.01 % steps) to the
target in pulses — degrees × the configured ``pulses_per_degree`` of each axis — and is
done when the status no longer says running and the position (0x75, pulses) is at the
target within two pulses. An alarm during the move ends it with the alarm's code and
text (0x70). ``stop()`` holds (0x83); the next move releases the hold. The joints read
are the position's pulses ÷ ``pulses_per_degree``.

UDP: every request carries a request id (1..255); its answer is the datagram with that
id. A datagram lost either way is sent again after ``request_timeout_s`` (``retries``
times; a move is an absolute target, so a repeat moves nowhere else), and an answer
whose id is not the one awaited (a late one, a duplicate) is dropped. No answer at all,
an ICMP "port unreachable", a refusal (the answer's status and added status, with their
meaning) and a datagram that is not HSES each end in one line naming the robot.
"""

from __future__ import annotations

import logging
import math
import select
import socket
import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers import yaskawa_hses_wire as wire
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription, host_port
from cellcal.drivers.stop_and_measure import N_JOINTS, ControllerState, HandshakeRobot

log = logging.getLogger("cellcal.drivers.yaskawa")

AT_TARGET_PULSES = 2  # the position is at the target within this many pulses per axis
MAX_PULSES_PER_DEGREE = 1e6
SERVO_ON_S = 5.0  # how long the servo may take to come on
SETTLE_S = 0.1  # standing at the target, not running, this long: the move is done


class YaskawaHsesOptions(RobotOptions):
    """``[robot]`` with ``driver = "yaskawa-hses"``: ``address`` host or host:port (UDP
    10040); ``pulses_per_degree`` one positive number per axis (the controller's
    encoder pulses per degree: required); ``robot`` the control group moved (R1..R8);
    a move not finished within ``move_timeout_s`` has failed; a datagram unanswered
    within ``request_timeout_s`` is sent again, ``retries`` times."""

    driver: Literal["yaskawa-hses"] = "yaskawa-hses"
    pulses_per_degree: list[float]
    robot: Annotated[int, Field(ge=1, le=8)] = 1
    move_timeout_s: Positive = 60.0
    request_timeout_s: Annotated[float, Field(gt=0, le=10)] = 0.5
    retries: Annotated[int, Field(ge=0, le=10)] = 3
    poll_s: Annotated[float, Field(gt=0, le=1)] = 0.05

    @field_validator("pulses_per_degree")
    @classmethod
    def _pulses(cls, values: list[float]) -> list[float]:
        return checked_pulses_per_degree(values)


def checked_pulses_per_degree(values: list[float]) -> list[float]:
    """``values`` when they are pulses per degree of each axis, else a ValueError whose
    text says which axis is wrong."""
    if len(values) != N_JOINTS:
        raise ValueError(f"one value per axis: {N_JOINTS}, got {len(values)}")
    for k, v in enumerate(values, start=1):
        if not (math.isfinite(v) and 0 < v <= MAX_PULSES_PER_DEGREE):
            raise ValueError(
                f"axis {k}: {v!r} is not a number of pulses per degree (positive, at most "
                f"{MAX_PULSES_PER_DEGREE:g}; the controller's parameters give it)"
            )
    return values


class YaskawaHsesRobot(HandshakeRobot):
    """A Yaskawa robot through the High-Speed Ethernet Server; see the module docstring."""

    family = "yaskawa-hses"

    def __init__(
        self,
        host: str,
        port: int = wire.PORT,
        *,
        name: str = "yaskawa-robot",
        options: YaskawaHsesOptions,
    ) -> None:
        o = options
        super().__init__(name, f"{host}:{port}", timeout_s=o.move_timeout_s, poll_s=o.poll_s)
        self.host, self.port = host, port
        self.options = o
        self.ppd = np.asarray(o.pulses_per_degree, dtype=np.float64)
        self._sock: socket.socket | None = None
        self._rid = 0
        self.resent = 0  # datagrams sent again after no answer
        self.dropped = 0  # answers dropped: not the one awaited

    @classmethod
    def from_options(cls, options: YaskawaHsesOptions, context: DeviceContext) -> YaskawaHsesRobot:
        host, port = host_port(options.address, wire.PORT)
        return cls(host, port, options=options)

    def describe(self) -> DeviceDescription:
        return DeviceDescription(ROBOT_NAME, self.family, self.where, "Yaskawa")

    # ------------------------------------------------------------------ datagrams

    def _request(
        self, command: int, instance: int, attribute: int, service: int, data: bytes = b""
    ) -> wire.Answer:
        """The answer to one request, sent again when no answer comes in time."""
        sock = self._sock
        if sock is None:
            raise self._error("not connected")
        self._rid = self._rid % 255 + 1
        raw = wire.encode_request(
            wire.Request(command, instance, attribute, service, self._rid, data)
        )
        timeout = self.options.request_timeout_s
        for attempt in range(1 + self.options.retries):
            if attempt:
                self.resent += 1
                log.info("%s: no answer to 0x%02X in %g s: sent again", self.name, command, timeout)
            try:
                sock.send(raw)
            except OSError as exc:
                raise self._error(f"cannot send ({exc.strerror or exc})") from None
            answer = self._answer(sock, timeout)
            if answer is not None:
                return answer
        raise self._error(
            f"no answer to command 0x{command:02X} in {1 + self.options.retries} tries of "
            f"{timeout:g} s: is the High-Speed Ethernet Server enabled and the address right?"
        )

    def _answer(self, sock: socket.socket, timeout: float) -> wire.Answer | None:
        deadline = time.monotonic() + timeout
        while True:
            wait = deadline - time.monotonic()
            if wait <= 0 or not select.select([sock], [], [], wait)[0]:
                return None
            try:
                raw = sock.recv(2048)
            except ConnectionRefusedError:
                raise self._error(
                    "nothing answers at this port (ICMP port unreachable): is the High-Speed "
                    "Ethernet Server enabled?"
                ) from None
            except OSError as exc:
                raise self._error(f"cannot receive ({exc.strerror or exc})") from None
            try:
                answer = wire.decode_answer(raw)
            except wire.HsesPacketError as exc:
                raise self._error(f"not an HSES answer: {exc}") from None
            if answer.request_id == self._rid:
                return answer
            self.dropped += 1  # a late answer of a request sent again, or a duplicate

    def _done(self, answer: wire.Answer, action: str) -> wire.Answer:
        if answer.status != 0:
            detail = self._alarm_text() if answer.added == 0x2060 else ""
            raise self._error(
                f"{action} refused: {answer.reason}" + (f": {detail}" if detail else "")
            )
        return answer

    def _control(self, command: int, instance: int, value: int, action: str) -> None:
        answer = self._request(command, instance, 1, wire.SET_SINGLE, wire.word(value))
        self._done(answer, action)

    def _status(self) -> wire.HsesStatus:
        answer = self._done(self._request(wire.STATUS, 1, 0, wire.GET_ALL), "status")
        try:
            return wire.status_of(answer.data)
        except wire.HsesPacketError as exc:
            raise self._error(str(exc)) from None

    def _alarm_text(self) -> str:
        """The latest alarm, ``alarm 4107 (OUT OF RANGE …)``; best effort."""
        answer = self._request(wire.ALARM, 1, 0, wire.GET_ALL)
        if answer.status != 0:
            return ""
        try:
            alarm = wire.alarm_of(answer.data)
        except wire.HsesPacketError:
            return ""
        if alarm.code == 0:
            return ""  # an error, not an alarm: the controller has no alarm to name
        return f"alarm {alarm.code}" + (f" ({alarm.text})" if alarm.text else "")

    # ------------------------------------------------------------------ the link

    def _open(self) -> None:
        """The socket, and a controller made ready where cellcal may: an alarm reset, an
        error cancelled, cellcal's hold released, the servo on."""
        self._close()
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.connect((self.host, self.port))
        except OSError as exc:
            self._close()
            raise self._error(f"cannot reach the controller ({exc.strerror or exc})") from None
        s = self._status()
        if s.teach or not s.remote or s.hold_pendant or s.hold_external:
            return  # connect says why
        if s.alarm:
            self._control(wire.RESET, wire.ALARM_RESET, 1, "alarm reset")
        if s.error:
            self._control(wire.RESET, wire.ERROR_CANCEL, 1, "error cancel")
        if s.hold_command:
            self._control(wire.HOLD_SERVO, wire.HOLD, wire.OFF, "hold release")
        s = self._status()
        if not s.servo_on and not s.alarm and not s.error:
            self._control(wire.HOLD_SERVO, wire.SERVO, wire.ON, "servo on")
            deadline = time.monotonic() + SERVO_ON_S
            while not self._status().servo_on and time.monotonic() < deadline:
                time.sleep(self.options.poll_s)

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # ------------------------------------------------------------------ the contract

    def _state(self) -> ControllerState:
        if self._sock is None:
            self._open()
        s = self._status()
        refusal = None
        if s.teach:
            refusal = "the controller is in TEACH: set PLAY and REMOTE with the pendant's key"
        elif not s.remote:
            refusal = "command remote is not set: select REMOTE on the pendant"
        elif s.hold_pendant or s.hold_external:
            which = "the pendant's" if s.hold_pendant else "an external"
            refusal = f"held by {which} HOLD: release it"
        elif s.alarm or s.error:
            what = self._alarm_text() or ("an alarm" if s.alarm else "an error")
            refusal = f"{what} is active: reset it on the pendant"
        elif not s.servo_on:
            refusal = "the servo is off and did not come on: check the safety circuit"
        fault = None if refusal is None else f"move failed: {refusal}"
        if fault is None and s.hold_command:  # a stop() during the move: it is abandoned
            fault = "move failed: held by a HOLD command (a stop)"
        return ControllerState(refusal, fault, s.running, 0, s.text)

    def _ready_to_move(self, target: Array) -> None:
        if self._sock is None:
            self._open()
        elif self._status().hold_command:  # left by stop()
            self._control(wire.HOLD_SERVO, wire.HOLD, wire.OFF, "hold release")
        super()._ready_to_move(target)

    def _move_and_settle(self, target: Array, speed: float) -> None:
        goal = self._pulses(np.degrees(target))
        self._send_move(np.degrees(target), speed, 0)
        deadline = time.monotonic() + self.timeout_s
        still_since: float | None = None  # standing at the target since (monotonic)
        while True:
            state = self._state()
            if state.fault is not None:
                raise self._error(state.fault)
            if state.moving:
                still_since = None
            elif np.abs(self._read_pulses() - goal).max() <= AT_TARGET_PULSES:
                # a controller may set its running bit late: the robot must stand there
                # for SETTLE_S before a move of a pulse or two counts as done
                still_since = still_since or time.monotonic()
                if time.monotonic() - still_since >= SETTLE_S:
                    return
            else:
                still_since = None
            if time.monotonic() > deadline:
                self._stop_quietly()
                raise self._error(f"move not done after {self.timeout_s:g} s ({state.text})")
            time.sleep(self.poll_s)

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        hundredths = max(1, min(10000, round(speed * 10000)))
        data = wire.pulse_move(self.options.robot, hundredths, list(self._pulses(target_deg)))
        answer = self._request(wire.PULSE_MOVE, wire.LINK_ABSOLUTE, 1, wire.SET_ALL, data)
        self._done(answer, "move")

    def _pulses(self, deg: Array) -> Array:
        out: Array = np.rint(np.asarray(deg, dtype=np.float64) * self.ppd).astype(np.int64)
        return out

    def _read_pulses(self) -> Array:
        answer = self._request(wire.POSITION, self.options.robot, 0, wire.GET_ALL)
        self._done(answer, "position")
        try:
            return np.array(wire.pulses_of(answer.data, N_JOINTS), dtype=np.int64)
        except wire.HsesPacketError as exc:
            raise self._error(str(exc)) from None

    def _read_joints_deg(self) -> Array:
        if self._sock is None:
            self._open()
        out: Array = self._read_pulses() / self.ppd
        return out

    def _joints_hint(self) -> str:
        return "are pulses_per_degree the controller's?"

    def _send_stop(self) -> None:
        """A HOLD: the robot stops; the next move releases it."""
        if self._sock is not None:
            self._control(wire.HOLD_SERVO, wire.HOLD, wire.ON, "hold")
