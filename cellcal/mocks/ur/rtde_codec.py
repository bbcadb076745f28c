"""RTDE on the wire (UR's Real-Time Data Exchange, TCP 30004): framing, message types,
packing by type, and the output-rate arithmetic of a 500 Hz controller. Stdlib only.

Every message is ``size:uint16 | type:uint8 | payload``, big-endian, ``size`` counting the
3-byte header. The two protocol versions differ in three places, which this module
encodes (UR's RTDE guide; UR's own clients parse them so):

* the output setup request carries the output frequency (double) before the names in v2
  only;
* the output setup reply starts with the output recipe id in v2 only (v1: the types);
* a data package from the controller starts with the recipe id in v2 only (v1 has one
  output recipe). A setup-inputs reply and a client's data package carry the input
  recipe id in both versions.

Text messages (``M``) are ``level | message`` in v1 and ``len | message | len | source |
level`` in v2.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Sequence
from typing import Any

RTDE_PORT = 30004

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

HEADER = struct.Struct(">HB")

#: The controller's cycle: 500 Hz on an e-Series, so the highest output frequency.
CYCLE_S = 0.002
MAX_FREQUENCY = 500.0

# Text message levels
EXCEPTION, ERROR, WARNING, INFO = 0, 1, 2, 3

#: struct codes of the RTDE types
TYPE_CODES = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}


def value_count(rtde_type: str) -> int:
    """How many scalars a value of the type packs to."""
    if rtde_type.startswith("VECTOR6"):
        return 6
    return 3 if rtde_type == "VECTOR3D" else 1


def frame(mtype: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(len(payload) + HEADER.size, mtype) + payload


def split_frames(buf: bytearray) -> Iterator[tuple[int, bytes]]:
    """Take the complete messages off the front of ``buf``; ValueError on a header whose
    size is smaller than the header itself (the stream cannot be resynchronised)."""
    while len(buf) >= HEADER.size:
        size, mtype = HEADER.unpack_from(buf)
        if size < HEADER.size:
            raise ValueError(f"RTDE message size {size} < {HEADER.size}")
        if len(buf) < size:
            return
        payload = bytes(buf[HEADER.size : size])
        del buf[:size]
        yield mtype, payload


def parse_names(raw: bytes) -> list[str]:
    """The comma-separated variable names of a setup request."""
    return [n.strip() for n in raw.decode("ascii", "replace").split(",") if n.strip()]


def parse_output_setup(protocol: int, payload: bytes) -> tuple[float | None, list[str]]:
    """(frequency, names) of a setup-outputs request; v1 has no frequency (None). A v2
    request too short for its frequency gives NaN, which is not a valid frequency."""
    if protocol < 2:
        return None, parse_names(payload)
    if len(payload) < 8:
        return math.nan, []
    return struct.unpack_from(">d", payload)[0], parse_names(payload[8:])


def valid_frequency(frequency: float) -> bool:
    return math.isfinite(frequency) and 0.0 < frequency <= MAX_FREQUENCY


def setup_outputs_reply(protocol: int, recipe_id: int, types: Sequence[str]) -> bytes:
    body = ",".join(types).encode()
    return body if protocol < 2 else struct.pack(">B", recipe_id) + body


def setup_inputs_reply(recipe_id: int, types: Sequence[str]) -> bytes:
    return struct.pack(">B", recipe_id) + ",".join(types).encode()


def success(ok: bool) -> bytes:
    """The one-byte answer to a version request, a start and a pause."""
    return b"\x01" if ok else b"\x00"


def data_struct(types: Sequence[str]) -> struct.Struct:
    """The packing of a recipe's values (without the recipe id)."""
    return struct.Struct(">" + "".join(TYPE_CODES[t] for t in types))


def flatten(values: Sequence[Any]) -> list[Any]:
    out: list[Any] = []
    for v in values:
        if isinstance(v, list | tuple):
            out.extend(v)
        else:
            out.append(v)
    return out


def data_package(protocol: int, recipe_id: int, st: struct.Struct, values: Sequence[Any]) -> bytes:
    """The payload of an output data package."""
    body = st.pack(*flatten(values))
    return body if protocol < 2 else struct.pack(">B", recipe_id) + body


def text_message(protocol: int, text: str, source: str = "RTDE", level: int = ERROR) -> bytes:
    msg = text.encode()[:255]
    if protocol < 2:
        return struct.pack(">B", level) + msg
    src = source.encode()[:255]
    return struct.pack(">B", len(msg)) + msg + struct.pack(">B", len(src)) + src + bytes([level])


class Decimation:
    """Which controller cycles a recipe of ``frequency`` Hz is sent on: a phase
    accumulator over the 500 Hz cycles, so a frequency that divides 500 is sent every
    500/f cycles exactly, and any other one every ⌊500/f⌋ or ⌈500/f⌉ cycles, keeping f
    on average. The first package goes out on the first cycle after the start."""

    def __init__(self, frequency: float) -> None:
        self.frequency = float(frequency)
        self.phase = MAX_FREQUENCY - self.frequency

    def restart(self) -> None:
        self.phase = MAX_FREQUENCY - self.frequency

    def due(self) -> bool:
        """Advance one cycle; whether a package goes out on it."""
        self.phase += self.frequency
        if self.phase >= MAX_FREQUENCY - 1e-9:
            self.phase -= MAX_FREQUENCY
            return True
        return False
