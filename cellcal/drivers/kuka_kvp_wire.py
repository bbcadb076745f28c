"""KUKAVARPROXY's wire format and the KRL value text it carries — no sockets.

KUKAVARPROXY (a program on the KRC's Windows side, TCP 7000) reads and writes KRL
variables by name; values travel as the text KRL shows them. Big-endian:

* request: ``u16 msg id, u16 length of the rest, u8 function (0 read, 1 write),
  u16 name length, name [, u16 value length, value]`` (the value of a write only);
* reply: ``u16 msg id, u16 length of the rest, u8 function, u16 value length, value,
  u16 0x0001, u8 ok`` (1 ok, 0 failed; the ``0x0001`` is the length of the ok byte; a
  failed request carries a value length 0 and no value; a write's reply carries the
  variable's value after the write).

KRL text is parsed strictly: a value that is not exactly the type asked for is one line
naming the variable and what was wrong (:class:`KrlTextError`), never a guess.
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass

from cellcal.errors import CellcalError

READ, WRITE = 0, 1
HEADER = struct.Struct(">HH")  # msg id, length of the rest
MAX_NAME = 255  # longer names are refused before sending: no KRL name is
MAX_VALUE = 4096
AXES = ("A1", "A2", "A3", "A4", "A5", "A6")
EXTERNAL = ("E1", "E2", "E3", "E4", "E5", "E6")
_REAL = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_INT = re.compile(r"[-+]?\d+")
_ENUM = re.compile(r"#[A-Z_][A-Z0-9_]*")
_TYPE = re.compile(r"([A-Z_][A-Z0-9_]*)\s*:")


class KrlTextError(CellcalError):
    """A KRL value that is not what was asked for."""


class KvpFrameError(CellcalError):
    """Bytes that are not a KUKAVARPROXY reply (or request)."""


@dataclass(frozen=True)
class Reply:
    msg_id: int
    function: int
    value: bytes
    ok: bool


def encode_request(msg_id: int, function: int, name: str, value: str | None = None) -> bytes:
    """One request: a read (``value`` None) or a write."""
    raw = name.encode("ascii")
    if not 0 < len(raw) <= MAX_NAME:
        raise KvpFrameError(f"variable name {name!r}: 1..{MAX_NAME} ASCII characters")
    body = struct.pack(">BH", function, len(raw)) + raw
    if function == WRITE:
        data = (value or "").encode("ascii")
        if len(data) > MAX_VALUE:
            raise KvpFrameError(f"value of {name}: {len(data)} bytes, at most {MAX_VALUE}")
        body += struct.pack(">H", len(data)) + data
    return HEADER.pack(msg_id & 0xFFFF, len(body)) + body


def encode_reply(msg_id: int, function: int, value: bytes, ok: bool) -> bytes:
    """One reply, as the proxy sends it (a failed one without its value)."""
    data = value if ok else b""
    body = struct.pack(">BH", function, len(data)) + data + struct.pack(">HB", 1, int(ok))
    return HEADER.pack(msg_id, len(body)) + body


def decode_reply(msg_id: int, length: int, rest: bytes) -> Reply:
    """The reply whose header was (``msg_id``, ``length``) and whose rest is ``rest``."""
    if len(rest) != length or length < 6:
        raise KvpFrameError(f"reply of {length} bytes after its header, {len(rest)} received")
    function, n = struct.unpack_from(">BH", rest)
    if 3 + n + 3 != length:
        raise KvpFrameError(f"reply says its value has {n} bytes but its length is {length}")
    tail, ok = struct.unpack_from(">HB", rest, 3 + n)
    if tail != 1 or ok not in (0, 1):
        raise KvpFrameError(f"reply ends {rest[-3:].hex(' ')}, not 00 01 and an ok byte")
    return Reply(msg_id, function, bytes(rest[3 : 3 + n]), bool(ok))


def decode_request(body: bytes) -> tuple[int, str, bytes | None]:
    """A request's rest after its header: (function, name, value of a write)."""
    if len(body) < 3:
        raise KvpFrameError("request too short")
    function, n = struct.unpack_from(">BH", body)
    if function not in (READ, WRITE) or 3 + n > len(body):
        raise KvpFrameError(f"request function {function} with a name of {n} bytes")
    name = body[3 : 3 + n].decode("ascii", "replace")
    if function == READ:
        if len(body) != 3 + n:
            raise KvpFrameError("read request with bytes after the name")
        return READ, name, None
    if len(body) < 5 + n:
        raise KvpFrameError("write request without a value length")
    (m,) = struct.unpack_from(">H", body, 3 + n)
    if len(body) != 5 + n + m:
        raise KvpFrameError(f"write request: value of {m} bytes, {len(body) - 5 - n} present")
    return WRITE, name, bytes(body[5 + n :])


# ------------------------------------------------------------------ KRL text


def _real(token: str, what: str) -> float:
    if not _REAL.fullmatch(token):
        raise KrlTextError(f"{what}: {token!r} is not a KRL REAL")
    value = float(token)
    if not math.isfinite(value):
        raise KrlTextError(f"{what}: {token!r} is not finite")
    return value


def parse_axes(text: str, what: str, type_name: str = "E6AXIS") -> list[float]:
    """A1..A6 (deg) of an AXIS or E6AXIS structure: ``{E6AXIS: A1 -39.86, ..., E6 0.0}``
    (the type name optional; E1..E6 allowed, and ignored). Anything else raises."""
    s = text.strip()
    if len(s) < 2 or s[0] != "{" or s[-1] != "}":
        raise KrlTextError(f"{what}: {text[:60]!r} is not a KRL structure {{...}}")
    inner = s[1:-1].strip()
    m = _TYPE.match(inner)
    if m:
        if m.group(1) not in ("AXIS", "E6AXIS"):
            raise KrlTextError(f"{what}: a {m.group(1)}, not an {type_name}")
        inner = inner[m.end() :]
    values: dict[str, float] = {}
    for part in inner.split(","):
        tokens = part.split()
        if len(tokens) != 2:
            raise KrlTextError(f"{what}: {part.strip()!r} is not 'component value'")
        key, number = tokens[0].upper(), tokens[1]
        if key not in AXES + EXTERNAL:
            raise KrlTextError(f"{what}: {tokens[0]!r} is not a component of {type_name}")
        if key in values:
            raise KrlTextError(f"{what}: {key} given twice")
        values[key] = _real(number, f"{what}, {key}")
    missing = [a for a in AXES if a not in values]
    if missing:
        raise KrlTextError(f"{what}: no {', '.join(missing)}")
    return [values[a] for a in AXES]


def format_axes(deg: list[float] | tuple[float, ...], type_name: str = "E6AXIS") -> str:
    """A1..A6 as KRL structure text; external axes at 0 for an E6AXIS."""
    parts = [f"{a} {float(v):.6f}" for a, v in zip(AXES, deg, strict=True)]
    if type_name == "E6AXIS":
        parts += [f"{e} 0.0" for e in EXTERNAL]
    return "{" + f"{type_name}: " + ", ".join(parts) + "}"


def parse_int(text: str, what: str) -> int:
    s = text.strip()
    if not _INT.fullmatch(s):
        raise KrlTextError(f"{what}: {text[:40]!r} is not a KRL INT")
    return int(s)


def parse_bool(text: str, what: str) -> bool:
    s = text.strip().upper()
    if s not in ("TRUE", "FALSE"):
        raise KrlTextError(f"{what}: {text[:40]!r} is not TRUE or FALSE")
    return s == "TRUE"


def parse_enum(text: str, what: str) -> str:
    s = text.strip().upper()
    if not _ENUM.fullmatch(s):
        raise KrlTextError(f"{what}: {text[:40]!r} is not a KRL enumeration value (#NAME)")
    return s


def parse_string(text: str) -> str:
    """A CHAR array as the proxy shows it (``"KR5ARC"``): without its quotes."""
    s = text.strip()
    return s[1:-1] if len(s) >= 2 and s[0] == s[-1] == '"' else s
