"""Yaskawa's High-Speed Ethernet Server on the wire (UDP, binary) — no sockets.

Every datagram is a 32-byte header, little-endian, then the data:

* ``"YERC"``, u16 header size (0x20), u16 data size, u8 reserved (3), u8 division (1:
  robot control, 2: file control), u8 ack (0: request, 1: answer), u8 request id, u32
  block number (0 in a request; 0x80000000 in a single-block answer), ``"99999999"``;
* a request's sub-header: u16 command, u16 instance, u8 attribute, u8 service, u16
  padding;
* an answer's: u8 service (the request's + 0x80), u8 status (0: done), u8 added-status
  size (in words), u8 padding, u16 added status (the reason), u16 padding.

The commands a campaign uses (robot control, UDP 10040): 0x72 status (two u32 words of
bits), 0x75 position (instance = robot: pulses; 52 bytes: data type, form, tool, user
frame, extended form, eight axes), 0x8B joint-pulse move (88 bytes: robot, station,
speed class, speed, eight axes, tool, three base and six station axes), 0x83 hold and
servo (instance 1 hold, 2 servo; 1 on, 2 off), 0x82 reset (instance 1 alarm, 2 error),
0x70 the latest alarm (code, data, type, time, text).

Sources: Yaskawa's HSES manuals 160766-1CD (FS100) and 178942-1CD (DX200/YRC1000) as the
open clients ``hsinkoyu/fs100`` (MIT) and PyPI ``yrcom`` cite them; the answer's
sub-header is fs100's (``yrcom`` reads the status one byte late, which only works on
status-0 answers).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from cellcal.errors import CellcalError

PORT = 10040
MAGIC = b"YERC"
HEADER_SIZE = 0x20
RESERVED = b"99999999"
ROBOT_CONTROL = 1
LAST_BLOCK = 0x80000000
MAX_DATA = 479  # the largest data part of one datagram

STATUS, POSITION, PULSE_MOVE, HOLD_SERVO, RESET, ALARM = 0x72, 0x75, 0x8B, 0x83, 0x82, 0x70
GET_ALL, SET_ALL, SET_SINGLE = 0x01, 0x02, 0x10
ON, OFF = 1, 2
HOLD, SERVO = 1, 2
ALARM_RESET, ERROR_CANCEL = 1, 2
LINK_ABSOLUTE = 1  # 0x8B's instance: joint interpolation to absolute pulses
SPEED_PERCENT = 0  # speed class of a link move: 0.01 % of the joints' maximum
AXES = 8

_HEADER = struct.Struct("<4sHHBBBBI8s")
_REQUEST = struct.Struct("<HHBBH")
_ANSWER = struct.Struct("<BBBBHH")
_STATUS = struct.Struct("<II")
_POSITION = struct.Struct("<13i")
_MOVE = struct.Struct("<22i")
_ALARM = struct.Struct("<III16s32s")

#: The added-status words a campaign can meet, in the manual's meaning (shortened).
ADDED = {
    0x1010: "command error",
    0x1012: "operand out of range",
    0x2010: "the manipulator is moving",
    0x2020: "hold by the programming pendant",
    0x2030: "hold by the playback panel",
    0x2040: "external hold",
    0x2050: "command hold",
    0x2060: "an error or alarm is active",
    0x2070: "servo off",
    0x2080: "incorrect mode (not PLAY)",
    0x2100: "command remote not set",
    0x3010: "turn on the servo",
    0x3450: "the servo cannot be turned on",
    0xA000: "undefined command",
    0xA001: "instance error",
    0xA002: "attribute error",
    0xB008: "control group setting error",
    0xB009: "speed setting error",
}
STATUS_TEXT = {
    0x01: "not executable now",
    0x08: "undefined command",
    0x09: "invalid element number",
    0x1F: "refused",
    0x28: "no such instance",
}


class HsesPacketError(CellcalError):
    """A datagram that is not an HSES answer (or request, for the twin)."""


@dataclass(frozen=True)
class Request:
    command: int
    instance: int
    attribute: int
    service: int
    request_id: int
    data: bytes = b""
    division: int = ROBOT_CONTROL


@dataclass(frozen=True)
class Answer:
    request_id: int
    service: int
    status: int
    added: int
    data: bytes
    division: int = ROBOT_CONTROL

    @property
    def reason(self) -> str:
        """``status 0x1F, added status 0x2070 (servo off)``."""
        text = f"status 0x{self.status:02X}"
        if self.added:
            meaning = ADDED.get(self.added)
            text += f", added status 0x{self.added:04X}" + (f" ({meaning})" if meaning else "")
        elif self.status in STATUS_TEXT:
            text += f" ({STATUS_TEXT[self.status]})"
        return text


def _header(size: int, ack: int, request_id: int, block: int, division: int) -> bytes:
    return _HEADER.pack(MAGIC, HEADER_SIZE, size, 3, division, ack, request_id, block, RESERVED)


def encode_request(r: Request) -> bytes:
    if len(r.data) > MAX_DATA:
        raise HsesPacketError(f"{len(r.data)} bytes of data: at most {MAX_DATA} in a datagram")
    head = _header(len(r.data), 0, r.request_id & 0xFF, 0, r.division)
    return head + _REQUEST.pack(r.command, r.instance, r.attribute, r.service, 0) + r.data


def encode_answer(a: Answer) -> bytes:
    head = _header(len(a.data), 1, a.request_id & 0xFF, LAST_BLOCK, a.division)
    size = 1 if a.added else 0
    return head + _ANSWER.pack(a.service, a.status, size, 0, a.added, 0) + a.data


def _split(raw: bytes, ack: int) -> tuple[tuple[int, ...], bytes]:
    if len(raw) < HEADER_SIZE:
        raise HsesPacketError(f"{len(raw)} bytes: shorter than the 32-byte header")
    magic, head, size, _, division, got, rid, block, _ = _HEADER.unpack_from(raw)
    if magic != MAGIC or head != HEADER_SIZE:
        raise HsesPacketError(f"no YERC header ({raw[:8]!r})")
    if got != ack:
        raise HsesPacketError(f"ack byte {got}, not {'an answer' if ack else 'a request'}")
    if len(raw) != HEADER_SIZE + size:
        raise HsesPacketError(f"data size {size} but {len(raw) - HEADER_SIZE} bytes follow")
    return (division, rid, block), raw[HEADER_SIZE:]


def decode_answer(raw: bytes) -> Answer:
    (division, rid, _), data = _split(raw, 1)
    service, status, _, _, added, _ = _ANSWER.unpack_from(raw, 24)
    return Answer(rid, service, status, added, data, division)


def decode_request(raw: bytes) -> Request:
    (division, rid, _), data = _split(raw, 0)
    command, instance, attribute, service, _ = _REQUEST.unpack_from(raw, 24)
    return Request(command, instance, attribute, service, rid, data, division)


# ---------------------------------------------------------------------- data parts


@dataclass(frozen=True)
class HsesStatus:
    """Command 0x72's two words, as the bits the driver reads."""

    data1: int
    data2: int

    step = property(lambda s: bool(s.data1 & 0x01))
    one_cycle = property(lambda s: bool(s.data1 & 0x02))
    auto = property(lambda s: bool(s.data1 & 0x04))
    running = property(lambda s: bool(s.data1 & 0x08))
    teach = property(lambda s: bool(s.data1 & 0x20))
    play = property(lambda s: bool(s.data1 & 0x40))
    remote = property(lambda s: bool(s.data1 & 0x80))
    hold_pendant = property(lambda s: bool(s.data2 & 0x02))
    hold_external = property(lambda s: bool(s.data2 & 0x04))
    hold_command = property(lambda s: bool(s.data2 & 0x08))
    alarm = property(lambda s: bool(s.data2 & 0x10))
    error = property(lambda s: bool(s.data2 & 0x20))
    servo_on = property(lambda s: bool(s.data2 & 0x40))

    @property
    def text(self) -> str:
        mode = "TEACH" if self.teach else "PLAY" if self.play else "REMOTE?"
        flags = [
            name
            for name, on in (
                ("running", self.running),
                ("remote", self.remote),
                ("servo on", self.servo_on),
                ("hold", self.hold_pendant or self.hold_external or self.hold_command),
                ("alarm", self.alarm),
                ("error", self.error),
            )
            if on
        ]
        return f"{mode}, " + (", ".join(flags) or "no flag")


def status_of(data: bytes) -> HsesStatus:
    if len(data) < _STATUS.size:
        raise HsesPacketError(f"status: {len(data)} bytes, not 8")
    return HsesStatus(*_STATUS.unpack_from(data))


def status_data(s: HsesStatus) -> bytes:
    return _STATUS.pack(s.data1, s.data2)


def pulses_of(data: bytes, n: int) -> list[int]:
    """The first ``n`` axes of a position record in pulses (data type 0)."""
    if len(data) < _POSITION.size:
        raise HsesPacketError(f"position: {len(data)} bytes, not 52")
    values = _POSITION.unpack_from(data)
    if values[0] != 0:
        raise HsesPacketError(f"position: data type {values[0]}, not pulses (0)")
    return list(values[5 : 5 + n])


def position_data(pulses: list[int], tool: int = 0) -> bytes:
    axes = [*pulses, *[0] * (AXES - len(pulses))]
    return _POSITION.pack(0, 0, tool, 0, 0, *axes)


def pulse_move(robot: int, speed_hundredths_pct: int, pulses: list[int]) -> bytes:
    """0x8B's data: a link move of robot ``robot`` to ``pulses`` at ``speed`` × 0.01 %."""
    axes = [*pulses, *[0] * (AXES - len(pulses))]
    return _MOVE.pack(robot, 0, SPEED_PERCENT, speed_hundredths_pct, *axes, 0, *[0] * 9)


@dataclass(frozen=True)
class PulseMove:
    robot: int
    station: int
    speed_class: int
    speed: int
    pulses: tuple[int, ...]
    tool: int


def pulse_move_of(data: bytes) -> PulseMove:
    if len(data) != _MOVE.size:
        raise HsesPacketError(f"pulse move: {len(data)} bytes, not 88")
    v = _MOVE.unpack(data)
    return PulseMove(v[0], v[1], v[2], v[3], tuple(v[4:12]), v[12])


def word(value: int) -> bytes:
    """A control command's data: one u32."""
    return struct.pack("<I", value)


def word_of(data: bytes) -> int:
    if len(data) < 4:
        raise HsesPacketError(f"{len(data)} bytes, not a 4-byte value")
    return int(struct.unpack_from("<I", data)[0])


@dataclass(frozen=True)
class AlarmData:
    code: int
    data: int
    kind: int
    time: str
    text: str


def alarm_of(data: bytes) -> AlarmData:
    if len(data) < _ALARM.size:
        raise HsesPacketError(f"alarm: {len(data)} bytes, not 60")
    code, value, kind, when, text = _ALARM.unpack_from(data)
    return AlarmData(code, value, kind, _text(when), _text(text))


def alarm_data(a: AlarmData) -> bytes:
    return _ALARM.pack(
        a.code, a.data, a.kind, a.time.encode("ascii")[:16], a.text.encode("latin-1")[:32]
    )


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()
