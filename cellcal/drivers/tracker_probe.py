"""A client of the tracker line protocol that takes every line as it comes, for the
conformance check (``tracker_conformance``): one request, the next line that is not an
event; events and lines that are not the protocol are recorded, never answers. Over the
driver's layers: a transport, its line framing and ``parse_line``."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from cellcal.drivers.line_framing import LineReader
from cellcal.drivers.tracker_protocol import (
    ERROR_TEXT,
    End,
    Err,
    Evt,
    Garbage,
    Message,
    Ok,
    Point,
    parse_line,
)
from cellcal.drivers.transport import Transport


def text_of(msg: Message | None, timeout: float) -> str:
    """A received message as the tracker sent it (None: nothing in time)."""
    if msg is None:
        return f"no answer within {timeout:g} s"
    if isinstance(msg, Ok):
        return f"OK {msg.payload}".strip()
    if isinstance(msg, Err):
        return f"ERR {msg.code} {msg.text} {msg.detail}".strip()
    if isinstance(msg, End):
        return f"END {msg.count}"
    if isinstance(msg, Point):
        return f"PT {msg.i} (version {msg.version})"
    return repr(msg)


def is_err(msg: Message | None, code: int) -> bool:
    return isinstance(msg, Err) and msg.code == code and msg.text == ERROR_TEXT[code]


@dataclass
class Probe:
    """One connection, line by line: events are recorded and skipped, lines that are
    not the protocol recorded (the check they came in fails) and skipped."""

    transport: Transport
    timeout: float
    lines: LineReader = field(init=False)
    events: list[Evt] = field(default_factory=list)
    junk: list[bytes] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.lines = LineReader(self.transport)

    def open(self) -> None:
        self.transport.open()
        self.lines.reset()

    def close(self) -> None:
        self.transport.close()

    def send(self, request: str | bytes) -> None:
        data = request.encode("ascii") if isinstance(request, str) else request
        self.transport.write(data + b"\n")

    def read(self, timeout: float | None = None) -> Message | None:
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while (line := self.lines.read_line(max(0.0, deadline - time.monotonic()))) is not None:
            msg = Garbage(line.raw, "too long") if line.overlong else parse_line(line.raw)
            if isinstance(msg, Evt):
                self.events.append(msg)
            elif isinstance(msg, Garbage):
                self.junk.append(line.raw[:48])
            else:
                return msg
        return None

    def ask(self, request: str | bytes, timeout: float | None = None) -> Message | None:
        self.send(request)
        return self.read(timeout)

    def drain(self, quiet: float = 0.3) -> None:
        """Drop what comes until ``quiet`` s pass without a line (at most the timeout)."""
        deadline = time.monotonic() + max(self.timeout, 1.0)
        while time.monotonic() < deadline and self.lines.read_line(quiet) is not None:
            continue  # each line read is dropped
