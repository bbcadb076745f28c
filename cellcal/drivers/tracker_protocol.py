"""The tracker line protocol, versions 1 and 2 (``docs/tracker.md``):
parsing of every line a tracker may send, and the error codes as exceptions.

A version 1 point is ``PT i t x y z``; a version 2 point adds the sample's covariance
(six terms, mm², the upper triangle row by row: xx xy xz yy yz zz) and the air the
tracker compensated it with (T °C, p hPa, RH %): 13 numbers after ``i``. Which one a
client may take is the version it asked for (``PROTO``); the parser reads both.

:func:`parse_line` never raises: whatever bytes arrive become one of the message types,
and anything that is not a valid line of the protocol becomes :class:`Garbage` — counted
and logged by the client, never taken for data.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from cellcal.errors import DeviceError, NoTargetError


@dataclass(frozen=True)
class Ok:
    payload: str


@dataclass(frozen=True)
class Err:
    code: int
    text: str
    detail: str


@dataclass(frozen=True)
class Evt:
    name: str
    payload: str


@dataclass(frozen=True)
class Point:
    """One ``PT`` line; ``cov`` (xx, xy, xz, yy, yz, zz; mm²) and ``air`` (°C, hPa, %RH)
    in version 2 only."""

    i: int
    t: float
    x: float
    y: float
    z: float
    cov: tuple[float, float, float, float, float, float] | None = None
    air: tuple[float, float, float] | None = None

    @property
    def version(self) -> int:
        """The protocol version whose form the line has."""
        return 1 if self.cov is None else 2


@dataclass(frozen=True)
class End:
    count: int


@dataclass(frozen=True)
class Garbage:
    raw: bytes
    reason: str


Message = Ok | Err | Evt | Point | End | Garbage


@dataclass(frozen=True)
class TrackerIdentity:
    maker: str
    model: str
    serial: str
    firmware: str


@dataclass(frozen=True)
class TrackerStatus:
    ready: bool
    beam: bool
    meteo: bool
    init: bool


@dataclass(frozen=True)
class Environment:
    """Air temperature (°C), pressure (hPa), relative humidity (%)."""

    temperature_c: float
    pressure_hpa: float
    humidity_pct: float


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_ERR = re.compile(r"ERR (\d+) ([A-Z_]+)(?: (.*))?")
_EVT = re.compile(r"EVT ([A-Z_]+)(?: (.*))?")
_NUM = re.compile(_NUMBER)
_END = re.compile(r"END (\d+)")


def _tuple3(values: list[float]) -> tuple[float, float, float]:
    return values[0], values[1], values[2]


def parse_versions(payload: str) -> tuple[int, ...] | None:
    """The versions a ``PROTO?`` answer announces (``1,2``: ascending, 1 among them), or
    None when the payload is not such a list."""
    parts = payload.strip().split(",")
    if not all(p.isdigit() and len(p) <= 3 for p in parts):
        return None
    versions = tuple(int(p) for p in parts)
    if versions[0] != 1 or list(versions) != sorted(set(versions)):
        return None
    return versions


def _point(raw: bytes, tokens: list[str]) -> Point | Garbage:
    """``PT``'s fields (split token by token: a regular expression of 13 numbers would
    backtrack for ever on a long wrong line)."""
    if len(tokens) not in (5, 14) or not tokens[0].isdigit():
        return Garbage(raw, "not a line of the protocol")
    if not all(_NUM.fullmatch(v) for v in tokens[1:]):
        return Garbage(raw, "not a line of the protocol")
    values = [float(v) for v in tokens[1:]]
    if not all(math.isfinite(v) for v in values):
        return Garbage(raw, "non-finite point")
    i, (t, x, y, z) = int(tokens[0]), values[:4]
    if len(values) == 4:
        return Point(i, t, x, y, z)
    c = values[4:10]
    return Point(i, t, x, y, z, (c[0], c[1], c[2], c[3], c[4], c[5]), _tuple3(values[10:]))


def parse_line(raw: bytes) -> Message:
    """One received line (terminator removed) as a protocol message."""
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        return Garbage(raw, "not ASCII")
    if any(ord(c) < 32 and c != "\t" for c in text):
        return Garbage(raw, "control characters")
    if text == "OK":
        return Ok("")
    if text.startswith("OK "):
        return Ok(text[3:])
    m = _ERR.fullmatch(text)
    if m:
        return Err(int(m.group(1)), m.group(2), m.group(3) or "")
    m = _EVT.fullmatch(text)
    if m:
        return Evt(m.group(1), m.group(2) or "")
    if text.startswith("PT "):
        return _point(raw, text[3:].split(" "))
    m = _END.fullmatch(text)
    if m:
        return End(int(m.group(1)))
    return Garbage(raw, "not a line of the protocol")


class TrackerError(DeviceError):
    """A tracker answered ``ERR <code> <TEXT>``."""

    code = 0

    def __init__(self, message: str, code: int | None = None, *, device: str | None = None) -> None:
        super().__init__(message, device=device)
        if code is not None:
            self.code = code


class TrackerBusyError(TrackerError):
    code = 1


class TrackerNotImplementedError(TrackerError):
    code = 2


class TrackerBadParameterError(TrackerError):
    code = 3


class TrackerUnknownCommandError(TrackerError):
    code = 4


class TrackerLostError(TrackerError):
    code = 38


class TrackerNotInitializedError(TrackerError):
    code = 39


class BeamBrokenError(TrackerError, NoTargetError):
    code = 40


class MeteoOutOfRangeError(TrackerError):
    code = 57


class TrackerTimeoutError(DeviceError):
    """No answer within the request's timeout."""


class TrackerSilentError(TrackerTimeoutError):
    """Nothing at all within the timeout: the link may be down (reconnect)."""


class TrackerProtocolError(TrackerTimeoutError):
    """No answer in time, but the device talks — not the protocol (garbage instead of
    an answer, a series that never ends): the link is up, reconnecting would not help."""


@dataclass
class Junk:
    """What a device sent, while one request waited for its answer, that is not a line
    of the protocol: how many bytes, how many lines, and the first bytes of the first."""

    size: int = 0
    lines: int = 0
    head: bytes = b""

    def add(self, raw: bytes, size: int) -> None:
        self.size += size
        self.lines += 1
        if not self.head:
            self.head = raw[:16]

    def error(
        self, where: str, waiting: str, *, pending: int = 0, head: bytes = b""
    ) -> TrackerProtocolError:
        """The one line that says so; ``pending``/``head``: an unfinished line too."""
        total = self.size + pending
        first = self.head or head
        return TrackerProtocolError(
            f"{where}: sent {total} bytes that are not the tracker line protocol while "
            f"{waiting} (first bytes: {first!r}); is it a tracker that speaks it (the "
            "bridge, the baud rate)?"
        )


#: The TEXT of each error code of the protocol (``ERR <code> <TEXT>``).
ERROR_TEXT = {
    1: "BUSY",
    2: "NOT_IMPLEMENTED",
    3: "BAD_PARAMETER",
    4: "UNKNOWN_COMMAND",
    38: "NO_TRACKER",
    39: "NOT_INITIALIZED",
    40: "BEAM_BROKEN",
    57: "METEO_OUT_OF_RANGE",
}

ERRORS: dict[int, type[TrackerError]] = {
    cls.code: cls
    for cls in (
        TrackerBusyError,
        TrackerNotImplementedError,
        TrackerBadParameterError,
        TrackerUnknownCommandError,
        TrackerLostError,
        TrackerNotInitializedError,
        BeamBrokenError,
        MeteoOutOfRangeError,
    )
}


def error_for(err: Err, request: str, where: str) -> TrackerError:
    cls = ERRORS.get(err.code, TrackerError)
    detail = f" {err.detail}" if err.detail else ""
    return cls(f"{where}: {request!r} answered ERR {err.code} {err.text}{detail}", err.code)
