"""Modbus/TCP as a register server speaks it: MBAP framing and the PDU codec, pure
functions over bytes — no sockets, no device (Modbus Application Protocol v1.1b3;
Modbus Messaging on TCP/IP Implementation Guide v1.0b).

A frame is the 7-byte MBAP header — transaction id, protocol id (0 = Modbus), length
(the bytes after the length field: the unit id and the PDU), unit id — then the PDU, a
function code and its data. :func:`split_frames` cuts a byte stream into frames however
the reads split or join them, keeping an incomplete frame's beginning for the next
read. A length below 2 or above 254 cannot be a Modbus frame: it is a framing error,
after which the stream cannot be resynchronised. Frames of another protocol id are
delimited and returned like the others; the caller drops them.

:func:`decode_request` reads the PDU of the register functions a robot controller
serves — 3 and 4 (read holding / input registers), 6 (write single register), 16 (write
multiple registers), 23 (read/write multiple registers) — and makes the checks the
spec makes before any address is looked at: the function code (exception 1, illegal
function; coils and discrete inputs included) and the quantities, byte count and PDU
length (exception 3, illegal data value). Addresses (exception 2) and processing
(exception 4) are the device's to check. :func:`reply_pdu` and :func:`exception_pdu`
build the answers (an exception: the request's function code + 0x80, then the code),
:func:`encode_frame` wraps a PDU in its MBAP header.

:func:`floats_to_registers` and :func:`registers_to_floats` are the usual float32
encoding in two registers (bytes big-endian within a register, either word order),
written with :mod:`struct` rather than a Modbus library's converters.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_HEADER = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id
HEADER_SIZE = _HEADER.size  # 7
_LENGTH_END = 6  # the length is known once the first 6 bytes are there
MIN_LENGTH = 2  # unit id + function code
MAX_LENGTH = 254  # unit id + the largest PDU (253 bytes)

READ_HOLDING = 3
READ_INPUT = 4
WRITE_SINGLE = 6
WRITE_MULTIPLE = 16
READ_WRITE = 23
FUNCTIONS = frozenset({READ_HOLDING, READ_INPUT, WRITE_SINGLE, WRITE_MULTIPLE, READ_WRITE})

MAX_READ = 125  # registers in one read (3, 4, and the read of 23)
MAX_WRITE = 123  # registers in one write multiple (16)
MAX_READ_WRITE = 121  # registers in the write of 23

# exception codes
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04
GATEWAY_TARGET_FAILED = 0x0B  # gateway target device failed to respond


class ModbusError(Exception):
    """A request to answer with an exception reply of ``code``."""

    def __init__(self, code: int, reason: str = "") -> None:
        super().__init__(f"exception {code:#04x}" + (f": {reason}" if reason else ""))
        self.code = code


@dataclass(frozen=True)
class Frame:
    """One MBAP frame: its header fields and its PDU (function code first)."""

    transaction: int
    protocol: int
    unit: int
    pdu: bytes


@dataclass(frozen=True)
class Split:
    """What :func:`split_frames` found: the whole frames, in order; ``rest``, the
    beginning of the next frame (to complete with the next read); ``error``, a framing
    error met after ``frames`` (the connection is to be closed)."""

    frames: tuple[Frame, ...]
    rest: bytes
    error: str | None = None


def split_frames(buffer: bytes | bytearray) -> Split:
    """Cut ``buffer`` (what is left of the last read, then the new bytes) into frames."""
    frames: list[Frame] = []
    pos = 0
    while len(buffer) - pos >= _LENGTH_END:
        (length,) = struct.unpack_from(">H", buffer, pos + 4)
        if not MIN_LENGTH <= length <= MAX_LENGTH:
            error = f"MBAP length {length} (a frame has {MIN_LENGTH}..{MAX_LENGTH})"
            return Split(tuple(frames), bytes(buffer[pos:]), error)
        end = pos + _LENGTH_END + length
        if end > len(buffer):
            break
        transaction, protocol, _, unit = _HEADER.unpack_from(buffer, pos)
        frames.append(Frame(transaction, protocol, unit, bytes(buffer[pos + HEADER_SIZE : end])))
        pos = end
    return Split(tuple(frames), bytes(buffer[pos:]))


def encode_frame(transaction: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    """``pdu`` behind its MBAP header."""
    return _HEADER.pack(transaction, protocol, len(pdu) + 1, unit) + pdu


@dataclass(frozen=True)
class Request:
    """A register request: what it writes (``values`` from ``write_address``; none when
    empty) and what it reads (``read_count`` from ``read_address``; none when 0).
    Function 23 does both, the write first."""

    function: int
    read_address: int = 0
    read_count: int = 0
    write_address: int = 0
    values: tuple[int, ...] = ()


def decode_request(pdu: bytes) -> Request:
    """The request in ``pdu``; ``ModbusError`` 1 for a function code not served, 3 for a
    quantity out of range, a byte count that does not match it, or a PDU of the wrong
    length."""
    function, body = pdu[0], pdu[1:]
    if function not in FUNCTIONS:
        raise ModbusError(ILLEGAL_FUNCTION, f"function code {function}")
    if function in (READ_HOLDING, READ_INPUT):
        address, count = _fields(">HH", body, exact=True)
        _quantity(count, MAX_READ)
        return Request(function, read_address=address, read_count=count)
    if function == WRITE_SINGLE:
        address, value = _fields(">HH", body, exact=True)
        return Request(function, write_address=address, values=(value,))
    if function == WRITE_MULTIPLE:
        address, count, nbytes = _fields(">HHB", body)
        _quantity(count, MAX_WRITE)
        values = _values(body[5:], count, nbytes)
        return Request(function, write_address=address, values=values)
    read_address, read_count, address, count, nbytes = _fields(">HHHHB", body)
    _quantity(read_count, MAX_READ)
    _quantity(count, MAX_READ_WRITE)
    values = _values(body[9:], count, nbytes)
    return Request(function, read_address, read_count, address, values)


def _fields(fmt: str, body: bytes, *, exact: bool = False) -> tuple[int, ...]:
    size = struct.calcsize(fmt)
    if len(body) < size or (exact and len(body) != size):
        raise ModbusError(ILLEGAL_VALUE, f"PDU data of {len(body)} bytes")
    return struct.unpack_from(fmt, body)


def _quantity(count: int, most: int) -> None:
    if not 1 <= count <= most:
        raise ModbusError(ILLEGAL_VALUE, f"quantity {count} (1..{most})")


def _values(data: bytes, count: int, nbytes: int) -> tuple[int, ...]:
    if nbytes != 2 * count or len(data) != nbytes:
        raise ModbusError(
            ILLEGAL_VALUE, f"byte count {nbytes}, {len(data)} bytes, for {count} registers"
        )
    return struct.unpack(f">{count}H", data)


def reply_pdu(request: Request, registers: Sequence[int]) -> bytes:
    """The normal reply to ``request``; ``registers``, the ones it read."""
    if request.function == WRITE_SINGLE:
        return struct.pack(">BHH", WRITE_SINGLE, request.write_address, request.values[0])
    if request.function == WRITE_MULTIPLE:
        return struct.pack(">BHH", WRITE_MULTIPLE, request.write_address, len(request.values))
    n = len(registers)
    return struct.pack(f">BB{n}H", request.function, 2 * n, *registers)


def exception_pdu(function: int, code: int) -> bytes:
    """The exception reply to a request of ``function``."""
    return bytes([function | 0x80, code])


def floats_to_registers(values: np.ndarray | list[float], word_order: str) -> list[int]:
    """float32 values → registers (two each), bytes big-endian within a register."""
    out: list[int] = []
    for v in values:
        hi, lo = struct.unpack(">HH", struct.pack(">f", float(v)))
        out += [hi, lo] if word_order == "big" else [lo, hi]
    return out


def registers_to_floats(registers: list[int], word_order: str) -> np.ndarray:
    """Registers (two a value) → float64 values of the float32s they hold."""
    out = []
    for i in range(0, len(registers), 2):
        a, b = registers[i], registers[i + 1]
        hi, lo = (a, b) if word_order == "big" else (b, a)
        out.append(struct.unpack(">f", struct.pack(">HH", hi, lo))[0])
    return np.array(out, dtype=np.float64)
