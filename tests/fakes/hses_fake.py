"""A plain fake Yaskawa Motoman controller serving the High-Speed Ethernet Server (HSES) on
UDP, for tests only.

Written from ``docs/robots.md`` ("Yaskawa through the High-Speed Ethernet Server") and the
header and data layouts of the open client ``hsinkoyu/fs100`` (MIT, after Yaskawa's HSES
manuals) alone, never from cellcal's own HSES driver, wire module or twin: a second,
independent controller to prove the driver against.

It is an asyncio ``DatagramProtocol`` on an event loop of its own thread. Nothing runs
between datagrams: the robot's state (motion, running bit, servo, limit alarm) is worked
out from the clock whenever a datagram arrives or a test asks. It serves 0x70 (the latest
alarm), 0x72 (status), 0x75 (position of robot 1 in pulses), 0x82 (alarm reset, error
cancel), 0x83 (hold, servo) and 0x8B (pulse move, link absolute); anything else it is sent
is answered with a status and recorded in ``unknown`` or ``malformed``.

Choices where the description leaves room (several deliberately off the obvious path):

- An answer's block number is 0x80000000 (the "last block" bit), never the request's 0.
  The sub-header's padding bytes (27, 30 and 31) carry 0x5A, not zero: only the added
  status word (bytes 28..29) counts, as the added-status size (1 word) says.
- Success is answered with status 0, added-status size 0 and added status 0. A refusal is
  status 0x1F, added-status size 1 and the reason; an unknown command is status 0x08, a
  request that breaks the documented layout status 0x09, an instance it does not serve
  0x28 (all three without an added status).
- Data1 of the status also carries 0x04 (continuous cycle) in PLAY; Data1 and Data2 are
  otherwise exactly the documented bits.
- The servo comes on ``servo_delay_s`` after 0x83 servo-on is accepted (brakes take time):
  until then the status says servo off and a move is refused with 0x2070.
- A move is answered at once. The robot starts moving ``motion_delay_s`` later; the running
  bit comes on only ``running_delay_s`` after the move was accepted (a controller may lag;
  a short move may never show it) and goes off ``settle_s`` after the robot reached the
  target. All axes start and end together on a cosine profile; the duration is the largest
  axis travel over ``max_deg_per_s`` x speed, times ``time_scale``.
- A move while one runs is accepted and re-planned from where the robot is.
- Standing, each 0x75 answer adds an independent -``jitter_pulses``..+``jitter_pulses``
  (seeded) to every axis; moving, the position is exact.
- A move whose path leaves the fake's limits (``LIMITS_DEG``: axis S +-120 deg, tighter than
  the KR 5 arc model's +-155) is accepted; the robot stops where it crosses the limit, the
  alarm ``4600 + axis`` "PULSE LIMIT OVER <axis>" is raised and the servo goes off. An
  alarm reset clears it (the robot stands on the limit, so inside), the servo stays off.
- 0x70 answers the latest alarm raised, also after it was reset (zeros if none ever was);
  its text is NUL-padded, the time ``YYYY/MM/DD HH:MM``.
- Refusals of a move, in this order: TEACH 0x2080, no remote 0x2100, the pendant's hold
  0x2030, an external hold 0x2040, a command hold 0x2050, alarm or error 0x2060, servo off
  0x2070, another robot 0xB008, a speed outside 1..10000 (0.01 %) 0xB009. Servo on is
  refused in TEACH (0x2080), without remote (0x2100), with an alarm (0x2060) and when
  ``servo_locked`` (0x3450). HOLD on stops a running move where it is (the move is
  cancelled: HOLD off does not resume it); servo off does the same.
- ``refuse_moves = (status, added status)`` refuses every 0x8B with that answer whatever
  the status says (as if the servo dropped between the driver's look and its move).
- Every ``lose_every``-th datagram is ignored, and every ``lose_every_move``-th 0x8B (a
  move is an absolute target, so its resend is harmless); every ``duplicate_every``-th
  datagram is answered twice (the copy 2 ms later); before every ``stale_every``-th
  answer, the previous answer sent (an older request id) is sent again. A datagram
  repeating the last one processed (same sender, id and bytes) is answered from memory,
  not executed again. A datagram without the YERC header is not answered at all.
- Fault switches, free to flip at any time: ``teach``, ``remote``, ``servo_locked``,
  ``pendant_hold``, ``external_hold``, ``error`` (Data2 0x20, cleared by 0x82 instance 2),
  ``refuse_moves``; ``raise_alarm()`` stops the robot with an alarm of the test's own.
- Every datagram is recorded in ``requests`` (lost ones too, with their fate), every 0x8B
  record in ``moves`` with the added status it got (0 when accepted).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

HEADER = struct.Struct("<4sHHBBBBI8s")  # YERC, header size, data size, 3, division, ack, id, block
REQ_SUB = struct.Struct("<HHBBH")  # command, instance, attribute, service, padding
ANS_SUB = struct.Struct("<BBBBHH")  # service, status, added size, pad, added status, pad
HEADER_SIZE = 0x20
ANSWER_BLOCK = 0x80000000
PAD = 0x5A
AXIS_NAMES = ("S", "L", "U", "R", "B", "T")
LIMITS_DEG = ((-120.0, 120.0), (-170.0, 60.0), (-10.0, 150.0), (-300.0, 300.0), (-125.0, 125.0),
              (-340.0, 340.0))  # fmt: skip
LIMIT_ALARM = 4600  # + the axis number (1..6)

TEACH_BIT, PLAY_BIT, REMOTE_BIT, RUNNING_BIT, CONTINUOUS_BIT = 0x20, 0x40, 0x80, 0x08, 0x04
PENDANT_HOLD, EXTERNAL_HOLD, COMMAND_HOLD = 0x02, 0x04, 0x08
ALARM_BIT, ERROR_BIT, SERVO_BIT = 0x10, 0x20, 0x40

# (attribute, service, data size) of the requests served
LAYOUT = {
    0x70: (0, 0x01, 0),
    0x72: (0, 0x01, 0),
    0x75: (0, 0x01, 0),
    0x82: (1, 0x10, 4),
    0x83: (1, 0x10, 4),
    0x8B: (1, 0x02, 88),
}


@dataclass(frozen=True)
class Request:
    at: float
    request_id: int
    command: int
    instance: int
    attribute: int
    service: int
    data: bytes
    fate: str  # "answered", "lost", "repeat", "unknown", "malformed"

    def u32(self) -> int:
        return struct.unpack_from("<I", self.data)[0] if len(self.data) >= 4 else -1


@dataclass(frozen=True)
class Move:
    robot: int
    station: int
    speed_class: int
    speed: int  # 0.01 %
    pulses: tuple[int, ...]  # 8 axes
    tool: int
    extra: tuple[int, ...]  # 3 base and 6 station axes
    refused: int  # the added status, 0 when accepted, -1 when ``refuse_moves`` refused it


@dataclass
class Alarm:
    code: int
    data: int
    kind: int
    stamp: str
    text: str


@dataclass
class _Segment:
    start: list[float]
    target: list[int]
    accepted: float
    begin: float
    duration: float
    cross: tuple[float, int, list[float]] | None  # when, axis (1-based), where


def _profile(s: float) -> float:
    return (1.0 - math.cos(math.pi * s)) / 2.0


class _Endpoint(asyncio.DatagramProtocol):
    def __init__(self, fake: HsesFake) -> None:
        self.fake = fake

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.fake._datagram(data, (str(addr[0]), int(addr[1])))

    def error_received(self, exc: Exception) -> None:
        pass  # an ICMP error from a client gone away: nothing to do


class HsesFake:
    def __init__(
        self,
        pulses_per_degree: Sequence[float],
        *,
        q0_deg: Sequence[float] = (0.0, -90.0, 90.0, 0.0, 0.0, 0.0),
        limits_deg: Sequence[tuple[float, float]] = LIMITS_DEG,
        time_scale: float = 0.05,
        max_deg_per_s: float = 150.0,
        servo_delay_s: float = 0.03,
        motion_delay_s: float = 0.01,
        running_delay_s: float = 0.025,
        settle_s: float = 0.01,
        jitter_pulses: int = 0,
        lose_every: int = 0,
        duplicate_every: int = 0,
        stale_every: int = 0,
        lose_every_move: int = 0,
        seed: int = 1988,
    ) -> None:
        if len(pulses_per_degree) != 6 or min(pulses_per_degree) <= 0:
            raise ValueError("six positive pulses per degree")
        self.ppd = [float(p) for p in pulses_per_degree]
        self.limits = [(float(lo), float(hi)) for lo, hi in limits_deg]
        self.time_scale = float(time_scale)
        self.max_deg_per_s = float(max_deg_per_s)
        self.servo_delay_s = float(servo_delay_s)
        self.motion_delay_s = float(motion_delay_s)
        self.running_delay_s = float(running_delay_s)
        self.settle_s = float(settle_s)
        self.jitter_pulses = int(jitter_pulses)
        self.lose_every = int(lose_every)
        self.duplicate_every = int(duplicate_every)
        self.stale_every = int(stale_every)
        self.lose_every_move = int(lose_every_move)
        # fault switches, free to flip from a test at any time
        self.teach = False
        self.remote = True
        self.servo_locked = False
        self.pendant_hold = False
        self.external_hold = False
        self.error = False
        #: (status, added status) every 0x8B is refused with whatever the status says
        self.refuse_moves: tuple[int, int] | None = None
        # what it saw
        self.requests: list[Request] = []
        self.moves: list[Move] = []
        self.malformed: list[str] = []
        self.unknown: list[str] = []
        self.lost = 0
        self.duplicated = 0
        self.stale_sent = 0
        self._pos = [round(q * p) * 1.0 for q, p in zip(q0_deg, self.ppd, strict=True)]
        self._seg: _Segment | None = None
        self._servo_at: float | None = None
        self._command_hold = False
        self._alarm: Alarm | None = None
        self._latest: Alarm | None = None
        self._count = 0
        self._move_count = 0
        self._last_key: tuple[tuple[str, int], bytes] | None = None
        self._last_answer = b""
        self._previous_answer = b""
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._transport: asyncio.DatagramTransport | None = None
        self._thread: threading.Thread | None = None

    # -- public ----------------------------------------------------------------------------

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        loop = asyncio.new_event_loop()
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                transport, _ = loop.run_until_complete(
                    loop.create_datagram_endpoint(lambda: _Endpoint(self), local_addr=(host, port))
                )
            except OSError as exc:
                failure.append(exc)
                ready.set()
                loop.close()
                return
            self._transport = transport
            ready.set()
            try:
                loop.run_forever()
            finally:
                transport.close()
                loop.run_until_complete(asyncio.sleep(0))
                loop.close()

        self._loop = loop
        self._thread = threading.Thread(target=run, daemon=True, name="hses-fake")
        self._thread.start()
        ready.wait(5.0)
        if failure:
            self._thread.join(2.0)
            raise failure[0]
        assert self._transport is not None
        addr = self._transport.get_extra_info("sockname")
        return str(addr[0]), int(addr[1])

    def stop(self) -> None:
        if self._loop is not None and self._thread is not None:
            with contextlib.suppress(RuntimeError):  # the loop is already closed
                self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5.0)

    def pulses(self) -> list[int]:
        """The robot's exact position (no jitter), 6 axes."""
        with self._lock:
            self._advance(time.monotonic())
            return [round(v) for v in self._pos]

    def q_deg(self) -> list[float]:
        return [v / p for v, p in zip(self.pulses(), self.ppd, strict=True)]

    @property
    def servo_on(self) -> bool:
        with self._lock:
            now = time.monotonic()
            self._advance(now)
            return self._servo(now)

    @property
    def command_hold(self) -> bool:
        with self._lock:
            return self._command_hold

    @property
    def alarm(self) -> Alarm | None:
        with self._lock:
            self._advance(time.monotonic())
            return self._alarm

    @property
    def moving(self) -> bool:
        with self._lock:
            self._advance(time.monotonic())
            return self._seg is not None

    def raise_alarm(self, code: int, text: str, data: int = 0) -> None:
        """An alarm from elsewhere (an e-stop): the robot stops where it is, servo off."""
        with self._lock:
            self._advance(time.monotonic())
            self._stand()
            self._raise(code, data, text)

    def sent(self, command: int, instance: int | None = None) -> list[Request]:
        """The requests processed (not lost) with this command (and instance)."""
        with self._lock:
            return [
                r
                for r in self.requests
                if r.command == command
                and (instance is None or r.instance == instance)
                and r.fate in ("answered", "repeat")
            ]

    # -- the robot -------------------------------------------------------------------------

    def _servo(self, now: float) -> bool:
        return self._servo_at is not None and now >= self._servo_at

    def _position_at(self, seg: _Segment, now: float) -> list[float]:
        if now <= seg.begin:
            return list(seg.start)
        s = 1.0 if seg.duration <= 0 else min(1.0, (now - seg.begin) / seg.duration)
        k = _profile(s)
        return [a + (b - a) * k for a, b in zip(seg.start, seg.target, strict=True)]

    def _advance(self, now: float) -> None:
        seg = self._seg
        if seg is None:
            return
        if seg.cross is not None and now >= seg.cross[0]:
            _, axis, where = seg.cross
            self._pos = list(where)
            self._seg = None
            self._raise(LIMIT_ALARM + axis, axis, f"PULSE LIMIT OVER {AXIS_NAMES[axis - 1]}")
            return
        self._pos = self._position_at(seg, now)
        if now >= seg.begin + seg.duration + self.settle_s:
            self._pos = [float(v) for v in seg.target]
            self._seg = None

    def _stand(self) -> None:
        self._seg = None

    def _raise(self, code: int, data: int, text: str) -> None:
        self._alarm = Alarm(code, data, 1, time.strftime("%Y/%m/%d %H:%M"), text)
        self._latest = self._alarm
        self._servo_at = None
        self._seg = None

    def _plan(self, target: list[int], speed: int, now: float) -> None:
        start = list(self._pos)
        travel = max(abs(b - a) / p for a, b, p in zip(start, target, self.ppd, strict=True))
        duration = travel / (self.max_deg_per_s * speed / 10000.0) * self.time_scale
        begin = now + self.motion_delay_s
        cross: tuple[float, int, list[float]] | None = None
        s_first, axis = 2.0, 0
        for i, (a, b) in enumerate(zip(start, target, strict=True)):
            lo, hi = (v * self.ppd[i] for v in self.limits[i])
            bound = hi if b > hi else lo if b < lo else None
            if bound is not None:  # the target is beyond a limit: where the path meets it
                s = max(0.0, (bound - a) / (b - a)) if b != a else 0.0
                if s < s_first:
                    s_first, axis = s, i + 1
        if s_first <= 1.0:
            where = [a + (b - a) * s_first for a, b in zip(start, target, strict=True)]
            when = begin + duration * math.acos(1.0 - 2.0 * s_first) / math.pi
            cross = (when, axis, where)
        self._seg = _Segment(start, target, now, begin, duration, cross)

    # -- the commands ----------------------------------------------------------------------

    def _status(self, now: float) -> bytes:
        d1 = REMOTE_BIT if self.remote else 0
        d1 |= TEACH_BIT if self.teach else PLAY_BIT | CONTINUOUS_BIT
        if self._seg is not None and now >= self._seg.accepted + self.running_delay_s:
            d1 |= RUNNING_BIT
        d2 = (PENDANT_HOLD if self.pendant_hold else 0) | (
            EXTERNAL_HOLD if self.external_hold else 0
        )
        d2 |= COMMAND_HOLD if self._command_hold else 0
        d2 |= ALARM_BIT if self._alarm is not None else 0
        d2 |= ERROR_BIT if self.error else 0
        d2 |= SERVO_BIT if self._servo(now) else 0
        return struct.pack("<II", d1, d2)

    def _position(self) -> bytes:
        axes = [round(v) for v in self._pos]
        if self._seg is None and self.jitter_pulses:
            j = self.jitter_pulses
            axes = [v + self._rng.randint(-j, j) for v in axes]
        return struct.pack("<5I8i", 0, 0, 0, 0, 0, *axes, 0, 0)

    def _latest_alarm(self) -> bytes:
        a = self._latest
        if a is None:
            return bytes(60)
        text = a.text.encode("ascii")[:32].ljust(32, b"\0")
        return struct.pack("<III", a.code, a.data, a.kind) + a.stamp.encode("ascii") + text

    def _move_refusal(self, now: float) -> int:
        if self.teach:
            return 0x2080
        if not self.remote:
            return 0x2100
        if self.pendant_hold:
            return 0x2030
        if self.external_hold:
            return 0x2040
        if self._command_hold:
            return 0x2050
        if self._alarm is not None or self.error:
            return 0x2060
        if not self._servo(now):
            return 0x2070
        return 0

    def _move(self, data: bytes, now: float) -> tuple[int, int]:
        v = struct.unpack("<22i", data)
        robot, station, speed_class, speed = v[0:4]
        pulses, tool, extra = v[4:12], v[12], v[13:22]
        refused = self._move_refusal(now)
        if self.refuse_moves is not None:
            self.moves.append(Move(robot, station, speed_class, speed, pulses, tool, extra, -1))
            return self.refuse_moves
        if not refused and robot != 1:
            refused = 0xB008
        if not refused and not 1 <= speed <= 10000:
            refused = 0xB009
        self.moves.append(Move(robot, station, speed_class, speed, pulses, tool, extra, refused))
        if station != 0 or speed_class != 0 or tool != 0 or any(extra) or any(pulses[6:]):
            self.malformed.append(f"0x8B record off the documented form: {v}")
        if not refused:
            self._plan(list(pulses[:6]), speed, now)
        return (0x1F if refused else 0), refused

    def _power(self, instance: int, value: int, now: float) -> tuple[int, int]:
        if instance == 1:  # HOLD
            self._command_hold = value == 1
            if value == 1:
                self._stand()
            return 0, 0
        if value == 2:  # servo off
            self._servo_at = None
            self._stand()
            return 0, 0
        for refused, why in (
            (self.teach, 0x2080),
            (not self.remote, 0x2100),
            (self._alarm is not None, 0x2060),
            (self.servo_locked, 0x3450),
        ):
            if refused:
                return 0x1F, why
        if self._servo_at is None:
            self._servo_at = now + self.servo_delay_s
        return 0, 0

    def _execute(self, cmd: int, instance: int, data: bytes, now: float) -> tuple[int, int, bytes]:
        """(status, added status, answer data) of a request already checked."""
        if cmd == 0x72:
            return 0, 0, self._status(now)
        if cmd == 0x75:
            return (0, 0, self._position()) if instance == 1 else (0x28, 0, b"")
        if cmd == 0x70:
            return (0, 0, self._latest_alarm()) if instance == 1 else (0x28, 0, b"")
        value = struct.unpack_from("<I", data)[0] if len(data) >= 4 else 0
        if cmd == 0x83:
            status, added = self._power(instance, value, now)
            return status, added, b""
        if cmd == 0x82:
            if instance == 1:
                self._alarm = None
            else:
                self.error = False
            return 0, 0, b""
        return *self._move(data, now), b""

    def _check(self, cmd: int, instance: int, attr: int, service: int, data: bytes) -> str | None:
        want = LAYOUT[cmd]
        if (attr, service, len(data)) != want:
            return f"0x{cmd:02X}: attribute/service/size {(attr, service, len(data))} != {want}"
        instances = {0x72: (1,), 0x83: (1, 2), 0x82: (1, 2), 0x8B: (1,)}.get(cmd)
        if instances is not None and instance not in instances:
            return f"0x{cmd:02X}: instance {instance}"
        if cmd == 0x83 and struct.unpack("<I", data)[0] not in (1, 2):
            return f"0x83: value {data.hex()}"
        if cmd == 0x82 and struct.unpack("<I", data)[0] != 1:
            return f"0x82: value {data.hex()}"
        return None

    # -- the wire --------------------------------------------------------------------------

    def _answer(self, rid: int, service: int, status: int, added: int, data: bytes) -> bytes:
        head = HEADER.pack(b"YERC", HEADER_SIZE, len(data), 3, 1, 1, rid, ANSWER_BLOCK, b"9" * 8)
        size = 1 if added else 0
        pad2 = PAD | PAD << 8
        sub = ANS_SUB.pack((service + 0x80) & 0xFF, status, size, PAD, added, pad2)
        return head + sub + data

    def _datagram(self, raw: bytes, addr: tuple[str, int]) -> None:
        now = time.monotonic()
        stale = b""
        with self._lock:
            self._count += 1
            k = self._count
            if len(raw) < HEADER_SIZE or raw[:4] != b"YERC":
                self.malformed.append(f"no YERC header: {raw[:40]!r}")
                return  # not HSES: a controller says nothing
            _, hsize, dsize, res, division, ack, rid, block, res2 = HEADER.unpack_from(raw)
            cmd, instance, attr, service, _ = REQ_SUB.unpack_from(raw, HEADER.size)
            data = raw[HEADER_SIZE:]
            expected = (HEADER_SIZE, len(data), 3, 1, 0, 0, b"9" * 8)
            header_fault = (hsize, dsize, res, division, ack, block, res2) != expected

            def record(fate: str) -> None:
                self.requests.append(Request(now, rid, cmd, instance, attr, service, data, fate))

            if cmd == 0x8B:
                self._move_count += 1
            lose_move = self.lose_every_move and self._move_count % self.lose_every_move == 0
            if (self.lose_every and k % self.lose_every == 0) or (cmd == 0x8B and lose_move):
                self.lost += 1
                record("lost")
                return
            key = (addr, raw)
            if key == self._last_key:
                record("repeat")
                answer = self._last_answer
            else:
                self._advance(now)
                if header_fault:
                    fault = f"header {(hsize, dsize, res, division, ack, block, res2)}"
                    self.malformed.append(fault)
                    fate, result = "malformed", (0x09, 0, b"")
                elif cmd not in LAYOUT:
                    self.unknown.append(f"command 0x{cmd:02X} instance {instance}")
                    fate, result = "unknown", (0x08, 0, b"")
                elif (fault := self._check(cmd, instance, attr, service, data)) is not None:
                    self.malformed.append(fault)
                    fate, result = "malformed", (0x09, 0, b"")
                else:
                    fate, result = "answered", self._execute(cmd, instance, data, now)
                record(fate)
                answer = self._answer(rid, service, *result)
                self._previous_answer, self._last_answer = self._last_answer, answer
                self._last_key = key
            old = self._previous_answer
            if self.stale_every and k % self.stale_every == 0 and old and old[11] != rid:
                stale = old  # an answer to an older request, late
                self.stale_sent += 1
            twice = bool(self.duplicate_every) and k % self.duplicate_every == 0
            if twice:
                self.duplicated += 1
        transport, loop = self._transport, self._loop
        assert transport is not None and loop is not None
        if stale:
            transport.sendto(stale, addr)
        transport.sendto(answer, addr)
        if twice:
            loop.call_later(0.002, transport.sendto, answer, addr)
