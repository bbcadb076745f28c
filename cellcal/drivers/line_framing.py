"""Line framing over a byte transport: ``\\n``-terminated ASCII lines, a ``\\r`` before
the ``\\n`` dropped, at most 256 bytes a line (a longer one is reported, not split)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from cellcal.drivers.transport import Transport

MAX_LINE = 256


@dataclass(frozen=True)
class Line:
    """A received line (without its terminator); ``overlong`` if it exceeded the limit
    (its content is then truncated)."""

    raw: bytes
    overlong: bool = False


class LineReader:
    def __init__(self, transport: Transport, max_line: int = MAX_LINE) -> None:
        self.transport = transport
        self.max_line = max_line
        self._buf = bytearray()
        self._discarding = False

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect)."""
        self._buf.clear()
        self._discarding = False

    def read_line(self, timeout: float) -> Line | None:
        """The next line, or None if none completed within ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw = bytes(self._buf[:nl])
                del self._buf[: nl + 1]
                if self._discarding:
                    self._discarding = False
                    return Line(raw[: self.max_line], overlong=True)
                if len(raw) > self.max_line + 1:
                    return Line(raw[: self.max_line], overlong=True)
                return Line(raw[:-1] if raw.endswith(b"\r") else raw)
            if len(self._buf) > self.max_line + 1:
                # An endless line: keep reading, but do not hold it all.
                self._discarding = True
                del self._buf[self.max_line :]
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._buf += self.transport.read(4096, left)

    def write_line(self, text: str) -> None:
        self.transport.write(text.encode("ascii") + b"\n")
