"""Leica emScon TPI packets (``docs/tracker.md``, "emScon"): the bytes of every command,
reply, result and event a campaign uses, both ways — the driver encodes commands and
decodes what the tracker sends; the twin decodes commands and encodes replies.

The wire: little-endian, Leica's ``#pragma pack(4)``, every C ``long`` and ``enum`` 4
bytes, doubles at 4-byte boundaries (so Python's ``struct`` with ``<`` and no padding is
exact). Every packet starts with ``int32 lPacketSize`` (the whole packet, header
included) and ``int32 type``; a command (type 0) then holds ``int32 command`` and its
parameters, and its reply ``int32 command, int32 status`` and the reply's values. There
is no sequence number: a reply is matched to its command by the command id alone.

Layouts are from the public copies of Leica's ``ES_C_API_Def.h`` (TPI 3.6), their sizes
checked against a compiler with ``pack(4)``; nothing here is copied from them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcal.calib.geometry import Array

# ---------------------------------------------------------------------- packet types

COMMAND = 0
ERROR = 1
SINGLE_RESULT = 2
NIVEL_RESULT = 6
REFLECTOR_POSITION = 7
STATUS_CHANGE = 8
SINGLE_RESULT2 = 9

# ---------------------------------------------------------------------- command ids

GET_SYSTEM_STATUS = 1
SET_UNITS = 5
GET_UNITS = 6
INITIALIZE = 7
SET_ENVIRONMENT_PARAMS = 20
GET_ENVIRONMENT_PARAMS = 21
SET_MEASUREMENT_MODE = 24
SET_COORDINATE_SYSTEM_TYPE = 26
SET_STATIONARY_MODE_PARAMS = 28
SET_REFLECTOR = 40
GET_REFLECTOR = 41
GET_REFLECTORS = 42
SET_SYSTEM_SETTINGS = 47
GET_SYSTEM_SETTINGS = 48
START_MEASUREMENT = 49
STOP_MEASUREMENT = 52
GO_BIRD_BATH = 54
FIND_REFLECTOR = 63
SET_STATISTIC_MODE = 80
GET_STATISTIC_MODE = 81
GET_MEASUREMENT_STATUS_INFO = 122
GET_TRACKER_INFO = 132
GET_METEO_STATION_INFO = 139

# ---------------------------------------------------------------------- codes

OK = 0
SERVER_BUSY = 1
WRONG_PARAMETER = 3
TRACKER_NOT_INITIALIZED = 39
METEO_OUT_OF_RANGE = 57
MEAS_STATUS_NOT_READY_ERROR = 10004
NO_STATIONARY_RESULT = 10009
MULTI_CONNECTIONS_NOT_ALLOWED = 10011
SENSOR_NOT_WARMED_UP = 10012
SENSOR_NOT_STABLE = 10013
SYSTEM_NOT_READY = 10014

MEAS_NOT_READY = 25
MEAS_BUSY = 26
MEAS_READY = 27
INITIALIZATION_STATUS_CHANGED = 151

REFLECTOR_FOUND = 2048
IN_FACE1 = 4096
INITIALIZED = 65536

#: units: length millimetre, angle degree, temperature Celsius, pressure hPa, humidity RH
MILLIMETRE, DEGREE, CELSIUS, HECTOPASCAL, RELATIVE_HUMIDITY = 1, 1, 0, 1, 0
WEATHER_NOT_CONNECTED, WEATHER_READ_ONLY, WEATHER_READ_AND_REFRACT = 0, 1, 2
STATIONARY = 0
RHR = 0
STATISTIC_STANDARD, STATISTIC_EXTENDED = 0, 1
TRACKER_PROCESSOR_INITIALIZED = 5
LASER_READY = 3
ADM_READY = 2

#: The results' codes and what they mean, for the one line a failure ends in.
STATUS_TEXT = {
    SERVER_BUSY: "server busy with another command",
    WRONG_PARAMETER: "wrong parameter",
    TRACKER_NOT_INITIALIZED: "tracker not initialized",
    METEO_OUT_OF_RANGE: "meteo data out of range",
    MEAS_STATUS_NOT_READY_ERROR: "measurement status not ready",
    NO_STATIONARY_RESULT: "no stationary result (beam broken or reflector lost)",
    MULTI_CONNECTIONS_NOT_ALLOWED: "another client is connected (one client only)",
    SENSOR_NOT_WARMED_UP: "sensor not warmed up",
    SENSOR_NOT_STABLE: "sensor not stable",
    SYSTEM_NOT_READY: "system not ready",
}


def status_text(status: int) -> str:
    return STATUS_TEXT.get(status, f"status {status}")


#: System status changes a campaign may see, in words.
CHANGE_TEXT = {
    2: "environment changed",
    6: "units changed",
    7: "reflector changed",
    8: "system settings changed",
    12: "coordinate system changed",
    17: "measurement mode changed",
    18: "stationary mode changed",
    24: "statistic mode changed",
    MEAS_NOT_READY: "not ready",
    MEAS_BUSY: "busy",
    MEAS_READY: "ready",
    INITIALIZATION_STATUS_CHANGED: "initialisation status changed",
    998: "server closing",
    999: "server started",
}


# ---------------------------------------------------------------------- layouts

HEADER = struct.Struct("<ii")
COMMAND_HEAD = struct.Struct("<iii")
REPLY_HEAD = struct.Struct("<iiii")
#: The largest packet either side accepts: a GetTrackerInfo reply is 164 bytes.
MAX_PACKET = 4096


@dataclass(frozen=True)
class Layout:
    """One command: its parameters after ``command`` and its reply's values after
    ``status`` (struct formats without the byte-order mark)."""

    name: str
    params: str = ""
    reply: str = ""

    @property
    def command_size(self) -> int:
        return COMMAND_HEAD.size + struct.calcsize("<" + self.params)

    @property
    def reply_size(self) -> int:
        return REPLY_HEAD.size + struct.calcsize("<" + self.reply)


LAYOUTS = {
    GET_SYSTEM_STATUS: Layout("GetSystemStatus", reply="10i"),
    SET_UNITS: Layout("SetUnits", params="5i"),
    GET_UNITS: Layout("GetUnits", reply="5i"),
    INITIALIZE: Layout("Initialize"),
    SET_ENVIRONMENT_PARAMS: Layout("SetEnvironmentParams", params="3d"),
    GET_ENVIRONMENT_PARAMS: Layout("GetEnvironmentParams", reply="3d"),
    SET_MEASUREMENT_MODE: Layout("SetMeasurementMode", params="i"),
    SET_COORDINATE_SYSTEM_TYPE: Layout("SetCoordinateSystemType", params="i"),
    SET_STATIONARY_MODE_PARAMS: Layout("SetStationaryModeParams", params="2i"),
    SET_REFLECTOR: Layout("SetReflector", params="i"),
    GET_REFLECTOR: Layout("GetReflector", reply="i"),
    GET_REFLECTORS: Layout("GetReflectors", reply="3id64s"),
    SET_SYSTEM_SETTINGS: Layout("SetSystemSettings", params="9i"),
    GET_SYSTEM_SETTINGS: Layout("GetSystemSettings", reply="9i"),
    START_MEASUREMENT: Layout("StartMeasurement"),
    STOP_MEASUREMENT: Layout("StopMeasurement"),
    GO_BIRD_BATH: Layout("GoBirdBath"),
    FIND_REFLECTOR: Layout("FindReflector", params="d"),
    SET_STATISTIC_MODE: Layout("SetStatisticMode", params="2i"),
    GET_STATISTIC_MODE: Layout("GetStatisticMode", reply="2i"),
    GET_MEASUREMENT_STATUS_INFO: Layout("GetMeasurementStatusInfo", reply="2i"),
    GET_TRACKER_INFO: Layout("GetTrackerInfo", reply="i64s5i3d2i2d3i"),
    GET_METEO_STATION_INFO: Layout("GetMeteoStationInfo", reply="i64s2i"),
}

SINGLE = struct.Struct("<iiiii17d")  # 156 bytes
SINGLE2 = struct.Struct("<iiiii23d")  # 204 bytes
ERROR_PACKET = struct.Struct("<iiii")  # 16 bytes
STATUS_PACKET = struct.Struct("<iii")  # 12 bytes
POSITION_PACKET = struct.Struct("<iii3d")  # 36 bytes
NIVEL_SIZE = 40

#: The size each packet type has (a command's reply: by its command, :data:`LAYOUTS`).
FIXED_SIZES = {
    ERROR: ERROR_PACKET.size,
    SINGLE_RESULT: SINGLE.size,
    NIVEL_RESULT: NIVEL_SIZE,
    REFLECTOR_POSITION: POSITION_PACKET.size,
    STATUS_CHANGE: STATUS_PACKET.size,
    SINGLE_RESULT2: SINGLE2.size,
}


class PacketError(ValueError):
    """Bytes that are not a packet of the protocol (the message says what is wrong)."""


# ---------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Command:
    """A command as a server reads it: its id and its parameters."""

    command: int
    params: tuple[Any, ...]


@dataclass(frozen=True)
class Reply:
    """A command's reply: its status and, for a Get* command, its values."""

    command: int
    status: int
    values: tuple[Any, ...]


@dataclass(frozen=True)
class ErrorPacket:
    """An error the tracker sends on its own (type 1): a beam break, for one."""

    command: int
    status: int


@dataclass(frozen=True)
class StatusChange:
    code: int


@dataclass(frozen=True)
class ReflectorPosition:
    xyz: tuple[float, float, float]


@dataclass(frozen=True)
class Measurement:
    """A stationary measurement's result (type 2, or 9 with covariances). Lengths in the
    units set (cellcal sets mm), meteo in °C, hPa and %RH."""

    status: int
    xyz: tuple[float, float, float]
    std: tuple[float, float, float]
    #: dCovar12, dCovar13, dCovar23 (type 9 only; None in a type 2 result)
    covar: tuple[float, float, float] | None
    temperature_c: float
    pressure_hpa: float
    humidity_pct: float

    def covariance(self) -> Array:
        """The 3×3 covariance (mm²): σ² on the diagonal, the covariances off it (zero
        for a type 2 result, which has none)."""
        c12, c13, c23 = self.covar if self.covar is not None else (0.0, 0.0, 0.0)
        s1, s2, s3 = (v * v for v in self.std)
        return np.array([[s1, c12, c13], [c12, s2, c23], [c13, c23, s3]], dtype=np.float64)


@dataclass(frozen=True)
class Ignored:
    """A packet of a type a campaign does not use (a nivel result): read and left."""

    type: int


Packet = Reply | ErrorPacket | StatusChange | ReflectorPosition | Measurement | Ignored


def event_text(packet: Packet) -> str:
    """A packet the tracker sent on its own, in words (``cellcal tracker``'s events)."""
    if isinstance(packet, StatusChange):
        return CHANGE_TEXT.get(packet.code, f"status change {packet.code}")
    if isinstance(packet, ErrorPacket):
        name = LAYOUTS[packet.command].name if packet.command in LAYOUTS else "no command"
        return f"error ({name}): {status_text(packet.status)}"
    if isinstance(packet, ReflectorPosition):
        return "reflector position"
    if isinstance(packet, Reply):
        return f"late reply to {LAYOUTS[packet.command].name}"
    if isinstance(packet, Measurement):
        return "a result nobody asked for"
    return f"packet of type {packet.type}"


# ---------------------------------------------------------------------- encoding


def _values(fmt: str, values: tuple[object, ...], what: str) -> bytes:
    try:
        return struct.pack("<" + fmt, *values)
    except struct.error as exc:
        raise PacketError(f"{what}: {exc}") from None


def encode_command(command: int, *params: object) -> bytes:
    """The bytes of a command (client to tracker)."""
    layout = LAYOUTS[command]
    body = _values(layout.params, params, layout.name)
    return COMMAND_HEAD.pack(layout.command_size, COMMAND, command) + body


def encode_reply(command: int, status: int, *values: object) -> bytes:
    """The bytes of a command's reply (tracker to client). A Get* reply always has its
    full size, its values zero when it failed: a client that reads the size its command
    expects (Leica's own examples do) must not be handed a short packet."""
    layout = LAYOUTS[command]
    if not values and layout.reply:
        values = tuple(_zero(c) for c in _fields(layout.reply))
    body = _values(layout.reply, values, layout.name)
    return REPLY_HEAD.pack(layout.reply_size, COMMAND, command, status) + body


def encode_error(command: int, status: int) -> bytes:
    return ERROR_PACKET.pack(ERROR_PACKET.size, ERROR, command, status)


def encode_status_change(code: int) -> bytes:
    return STATUS_PACKET.pack(STATUS_PACKET.size, STATUS_CHANGE, code)


def encode_measurement(m: Measurement) -> bytes:
    """A type 9 result when ``m`` has covariances, else a type 2 one."""
    (x, y, z), (s1, s2, s3) = m.xyz, m.std
    total = float(np.sqrt(s1 * s1 + s2 * s2 + s3 * s3))
    meteo = (m.temperature_c, m.pressure_hpa, m.humidity_pct)
    head = [x, y, z, s1, s2, s3, total]
    pointing = [0.0, 0.0, 0.0]  # pointing errors: none to report
    if m.covar is None:
        doubles = [*head, *pointing, s1, s2, s3, total, *meteo]  # a-priori σ: the σ
        return SINGLE.pack(SINGLE.size, SINGLE_RESULT, m.status, STATIONARY, 0, *doubles)
    covar = list(m.covar)
    doubles = [*head, *covar, *pointing, s1, s2, s3, total, *covar, *meteo]
    return SINGLE2.pack(SINGLE2.size, SINGLE_RESULT2, m.status, STATIONARY, 0, *doubles)


def _fields(fmt: str) -> list[str]:
    """``"3id64s"`` → ``["i", "i", "i", "d", "64s"]``."""
    out, count = [], ""
    for ch in fmt:
        if ch.isdigit():
            count += ch
        elif ch == "s":
            out.append(f"{count}s")
            count = ""
        else:
            out += [ch] * int(count or 1)
            count = ""
    return out


def _zero(code: str) -> object:
    return b"" if code.endswith("s") else 0.0 if code == "d" else 0


def encode_name(name: str) -> bytes:
    """A name as the tracker sends it: 32 UTF-16LE code units, zero padded."""
    raw = name.encode("utf-16-le")[:62]
    return raw + b"\0" * (64 - len(raw))


def decode_name(raw: bytes) -> str:
    """The name of a 64-byte UTF-16LE field, up to its first NUL."""
    text = raw.decode("utf-16-le", errors="replace")
    return text.split("\0", 1)[0]


# ---------------------------------------------------------------------- decoding


def packet_size(header: bytes) -> tuple[int, int]:
    """The size and type a packet's first 8 bytes announce; refused when no packet of
    the protocol has that size or type."""
    size, kind = HEADER.unpack(header)
    if size < HEADER.size or size > MAX_PACKET:
        raise PacketError(f"a packet announces {size} bytes")
    if kind in FIXED_SIZES and size != FIXED_SIZES[kind]:
        raise PacketError(f"a type {kind} packet of {size} bytes (it has {FIXED_SIZES[kind]})")
    if kind != COMMAND and kind not in FIXED_SIZES:
        raise PacketError(f"a packet of unknown type {kind} ({size} bytes)")
    return size, kind


def decode_packet(data: bytes) -> Packet:
    """One whole packet from the tracker; :class:`PacketError` when its size or content
    is not the protocol's."""
    size, kind = packet_size(data[: HEADER.size])
    if len(data) != size:
        raise PacketError(f"a packet of {len(data)} bytes announces {size}")
    if kind == COMMAND:
        return _decode_reply(data)
    if kind == ERROR:
        _, _, command, status = ERROR_PACKET.unpack(data)
        return ErrorPacket(command, status)
    if kind == STATUS_CHANGE:
        return StatusChange(STATUS_PACKET.unpack(data)[2])
    if kind == REFLECTOR_POSITION:
        _, _, _, x, y, z = POSITION_PACKET.unpack(data)
        return ReflectorPosition((x, y, z))
    if kind == SINGLE_RESULT:
        v = SINGLE.unpack(data)
        d = v[5:]
        return Measurement(v[2], d[0:3], d[3:6], None, d[14], d[15], d[16])
    if kind == SINGLE_RESULT2:
        v = SINGLE2.unpack(data)
        d = v[5:]
        return Measurement(v[2], d[0:3], d[3:6], d[7:10], d[20], d[21], d[22])
    return Ignored(kind)


def _decode_reply(data: bytes) -> Reply:
    if len(data) < REPLY_HEAD.size:
        raise PacketError(f"a reply of {len(data)} bytes (a reply has at least 16)")
    _, _, command, status = REPLY_HEAD.unpack_from(data)
    layout = LAYOUTS.get(command)
    if layout is None:
        raise PacketError(f"a reply to command {command}, which cellcal never sends")
    if len(data) == REPLY_HEAD.size and status != OK:
        return Reply(command, status, ())  # a failing Get* answered short: its status
    if len(data) != layout.reply_size:
        raise PacketError(
            f"a {layout.name} reply of {len(data)} bytes (it has {layout.reply_size})"
        )
    return Reply(command, status, struct.unpack_from("<" + layout.reply, data, REPLY_HEAD.size))


def decode_command(data: bytes) -> Command:
    """One whole command (what a tracker reads); :class:`PacketError` when it is not one
    of :data:`LAYOUTS` with its exact size."""
    size, kind = HEADER.unpack_from(data)
    if kind != COMMAND or len(data) < COMMAND_HEAD.size:
        raise PacketError(f"a packet of type {kind} and {size} bytes is not a command")
    command = COMMAND_HEAD.unpack_from(data)[2]
    layout = LAYOUTS.get(command)
    if layout is None:
        raise PacketError(f"command {command} is not one this tracker serves")
    if size != len(data) or size != layout.command_size:
        raise PacketError(f"{layout.name} of {len(data)} bytes (it has {layout.command_size})")
    params = struct.unpack_from("<" + layout.params, data, COMMAND_HEAD.size)
    return Command(command, params)
