"""Line framing over a byte transport: ``\\n``-terminated ASCII lines, a ``\\r`` before
the ``\\n`` dropped, at most 256 bytes a line (a longer one is reported, not split, and
never held whole: its head is kept, the rest counted and dropped)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from cellcal.drivers.transport import Transport

MAX_LINE = 256
#: how many first bytes of an unfinished line :attr:`LineReader.head` shows
HEAD = 16


@dataclass(frozen=True)
class Line:
    """A received line (without its terminator); ``overlong`` if it exceeded the limit
    (its content is then truncated); ``size``, the bytes it took on the wire (its
    terminator and what was dropped of it included)."""

    raw: bytes
    overlong: bool = False
    size: int = 0


class LineReader:
    def __init__(self, transport: Transport, max_line: int = MAX_LINE) -> None:
        self.transport = transport
        self.max_line = max_line
        self._buf = bytearray()
        self._dropped = 0  # bytes of the current overlong line not kept

    def reset(self) -> None:
        """Forget buffered bytes (after a reconnect)."""
        self._buf.clear()
        self._dropped = 0

    @property
    def pending(self) -> int:
        """Bytes received of a line not finished yet (dropped ones included)."""
        return len(self._buf) + self._dropped

    @property
    def head(self) -> bytes:
        """The first bytes of the line not finished yet."""
        return bytes(self._buf[:HEAD])

    def read_line(self, timeout: float) -> Line | None:
        """The next line, or None if none completed within ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw = bytes(self._buf[:nl])
                del self._buf[: nl + 1]
                size, dropped = nl + 1 + self._dropped, self._dropped
                self._dropped = 0
                if raw.endswith(b"\r"):
                    raw = raw[:-1]
                if dropped or len(raw) > self.max_line:
                    return Line(raw[: self.max_line], overlong=True, size=size)
                return Line(raw, size=size)
            if len(self._buf) > self.max_line + 1:
                # An endless line: keep reading, but do not hold it all.
                self._dropped += len(self._buf) - self.max_line
                del self._buf[self.max_line :]
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._buf += self.transport.read(4096, left)

    def write_line(self, text: str) -> None:
        self.transport.write(text.encode("ascii") + b"\n")
