"""The Yaskawa twin: a YRC1000's High-Speed Ethernet Server on UDP, serving the simulated
cell's robot, for the ``yaskawa-hses`` driver, ``cellcal mock yaskawa-hses`` and
``cellcal run --mock``.

Every request datagram (``drivers/yaskawa_hses_wire``) gets one answer with its request
id, to the address it came from: the status (0x72: PLAY or TEACH, command remote,
running, hold, alarm, servo on), the position in pulses (0x75, the configured robot's
instance; pulses = degrees × the configured ``pulses_per_degree``), the joint-pulse move
(0x8B: answered at once; the robot then moves and the status says running until it
stands still), hold and servo (0x83), alarm reset and error cancel (0x82), the latest
alarm (0x70). A move is refused, as a controller refuses it, in TEACH (added status
0x2080), without command remote (0x2100), with an alarm (0x2060), the servo off (0x2070),
held (0x2050), while moving (0x2010), for another robot (0xB008) or at a speed outside
0.01..100 % (0xB009); a request of another command answers status 0x08, a datagram that
is not HSES is dropped. The controller starts with the servo off.

The motion is the controller model of the KUKA, ABB and FANUC twins (``mocks/kuka/krc.py``:
the cell's limits and speed, its faults): a target beyond a limit, or the cell's
``robot_protective_stop_every``, stops the robot with an alarm (code 4100 + the axis, or
4000; the twin's own codes and texts) until it is reset.

Faults (:class:`HsesFaults`, settable at run time): TEACH, command remote off, a servo
that cannot be turned on, every N-th request datagram lost (no answer) and every N-th
answer sent twice.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import numpy as np

from cellcal.drivers import yaskawa_hses_wire as wire
from cellcal.drivers.kuka_kvp_wire import format_axes
from cellcal.mocks.kuka.krc import KrcController, krc_for_cell
from cellcal.mocks.twins import YASKAWA_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.yaskawa_hses import YaskawaHsesOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.yaskawa")

POLL_S = 0.05
REFUSED = 0x1F  # the status of a refusal whose reason is the added status


@dataclass
class HsesFaults:
    teach: bool = False
    remote: bool = True
    servo_locked: bool = False  # the servo cannot be turned on (added status 0x3450)
    lose_every: int = 0  # every N-th request datagram gets no answer (0: none)
    duplicate_every: int = 0  # every N-th answer is sent twice (0: none)


class HsesTwin:
    """The High-Speed Ethernet Server of a :class:`KrcController`; see the module
    docstring."""

    def __init__(
        self, controller: KrcController, pulses_per_degree: list[float], *, robot: int = 1
    ) -> None:
        self.controller = controller
        self.ppd = np.asarray(pulses_per_degree, dtype=np.float64)
        self.robot = robot
        self.faults = HsesFaults()
        self.servo_on = False
        self.hold = False
        self.alarm: wire.AlarmData | None = None
        self.requests: deque[wire.Request] = deque(maxlen=10000)
        self.lost = self.duplicated = 0
        self._count = 0
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))
        except OSError:
            sock.close()
            raise
        sock.settimeout(POLL_S)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name="yaskawa-hses-twin", daemon=True)
        self._thread.start()
        bound = sock.getsockname()
        return str(bound[0]), int(bound[1])

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._sock is not None:
            self._sock.close()

    def _serve(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                raw, peer = sock.recvfrom(2048)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                request = wire.decode_request(raw)
            except wire.HsesPacketError as exc:
                log.info("yaskawa twin: dropped: %s", exc)
                continue
            self._count += 1
            f = self.faults
            if f.lose_every and self._count % f.lose_every == 0:
                self.lost += 1
                continue
            self.requests.append(request)
            answer = wire.encode_answer(self._handle(request))
            copies = 2 if f.duplicate_every and self._count % f.duplicate_every == 0 else 1
            self.duplicated += copies - 1
            for _ in range(copies):
                try:
                    sock.sendto(answer, peer)
                except OSError as exc:
                    log.info("yaskawa twin: cannot answer %s: %s", peer, exc)

    # ------------------------------------------------------------------ requests

    def _handle(self, r: wire.Request) -> wire.Answer:
        c = self.controller
        with c.lock:
            self._step()
            data = b""
            status, added = 0, 0
            try:
                if r.division != wire.ROBOT_CONTROL:
                    status = 0x08
                elif r.command == wire.STATUS:
                    data = wire.status_data(self.status())
                elif r.command == wire.POSITION:
                    if r.instance != self.robot:
                        status, added = REFUSED, 0xA001
                    else:
                        q = np.asarray(c.q_now(), dtype=np.float64)
                        data = wire.position_data([int(v) for v in np.rint(q * self.ppd)])
                elif r.command == wire.PULSE_MOVE:
                    added = self._move(r)
                elif r.command == wire.HOLD_SERVO:
                    added = self._hold_servo(r.instance, wire.word_of(r.data))
                elif r.command == wire.RESET:
                    if r.instance == wire.ALARM_RESET:
                        self._reset()
                elif r.command == wire.ALARM:
                    a = self.alarm or wire.AlarmData(0, 0, 0, "", "")
                    data = wire.alarm_data(a)
                else:
                    status = 0x08
            except wire.HsesPacketError:
                status, added = REFUSED, 0x1013
            if added:
                status = REFUSED
            return wire.Answer(r.request_id, r.service + 0x80, status, added, data, r.division)

    def status(self) -> wire.HsesStatus:
        f, c = self.faults, self.controller
        d1 = (0x20 if f.teach else 0x44) | (0x80 if f.remote else 0)
        d1 |= 0x08 if c.move is not None else 0
        d2 = (0x08 if self.hold else 0) | (0x10 if self.alarm else 0)
        d2 |= 0x40 if self.servo_on else 0
        return wire.HsesStatus(d1, d2)

    def _move(self, r: wire.Request) -> int:
        f, c = self.faults, self.controller
        m = wire.pulse_move_of(r.data)
        refusals = (
            (r.instance != wire.LINK_ABSOLUTE or r.service != wire.SET_ALL, 0xA001),
            (f.teach, 0x2080),
            (not f.remote, 0x2100),
            (self.alarm is not None, 0x2060),
            (not self.servo_on, 0x2070),
            (self.hold, 0x2050),
            (c.move is not None, 0x2010),
            (m.robot != self.robot or m.station != 0, 0xB008),
            (m.speed_class != wire.SPEED_PERCENT or not 1 <= m.speed <= 10000, 0xB009),
        )
        for refused, added in refusals:
            if refused:
                return added
        n = len(c.q)
        target = [m.pulses[k] / self.ppd[k] for k in range(n)]
        c.write("CC_TARGET", format_axes(target))
        c.write("CC_SPEED", str(max(1, min(100, math.ceil(m.speed / 100)))))
        c.write("CC_SEQ", str(c.ack % 0xFFFF + 1))
        self._step()
        return 0

    def _hold_servo(self, instance: int, value: int) -> int:
        on = value == wire.ON
        if instance == wire.HOLD:
            self.hold = on
            if on:
                self._brake()
        elif instance == wire.SERVO:
            if on and self.faults.servo_locked:
                return 0x3450
            self.servo_on = on
            self.controller.faults.drives_on = on
        return 0

    def _brake(self) -> None:
        c = self.controller
        if c.move is not None:
            c.write("CC_STOP", "TRUE")
            c.step()

    def _reset(self) -> None:
        c = self.controller
        self.alarm = None
        c.acknowledge_stop_message()
        c.ack = c.seq  # the move that raised the alarm is dropped, not taken up again

    def _step(self) -> None:
        c = self.controller
        c.faults.drives_on = self.servo_on
        c.step()
        if c.stop_message and self.alarm is None:
            self.alarm = self._alarm_for(c.target)

    def _alarm_for(self, target: np.ndarray) -> wire.AlarmData:
        when = datetime.now(UTC).strftime("%Y/%m/%d %H:%M")
        for k, (v, (lo, hi)) in enumerate(zip(target, self.controller.limits, strict=True)):
            if not lo <= v <= hi:
                return wire.AlarmData(4100 + k + 1, k + 1, 1, when, f"LIMIT AXIS {k + 1} (twin)")
        return wire.AlarmData(4000, 0, 1, when, "EXTERNAL STOP (twin)")


def serve(options: YaskawaHsesOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured Yaskawa robot on an ephemeral UDP port of a loopback
    address."""
    controller = krc_for_cell(options.home_deg, cell, time_scale)
    twin = HsesTwin(controller, options.pulses_per_degree, robot=options.robot)
    host, port = twin.start(YASKAWA_HOST, 0)
    return RunningTwin(options.model_copy(update={"address": f"{host}:{port}"}), twin)
