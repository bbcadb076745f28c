"""A scripted transport (PyMeasure's ``expected_protocol`` idea): the test lists the exact
request lines the driver must send and the lines the tracker answers with."""

from __future__ import annotations

from collections import deque

from cellcal.drivers.transport import TransportError


class ScriptedTransport:
    url = "scripted://"

    def __init__(self, pairs, *, drop_at=None):
        """``pairs``: [(request or None, [reply lines...]), ...]; a None request means the
        replies arrive unsolicited. ``drop_at``: raise TransportError when the k-th
        request is written (the link dropped)."""
        self.pairs = deque(pairs)
        self.written: list[str] = []
        self._out = bytearray()
        self.opened = 0
        self._open = False
        self.drop_at = drop_at

    @property
    def is_open(self):
        return self._open

    def open(self):
        self.opened += 1
        self._open = True

    def close(self):
        self._open = False

    def write(self, data: bytes):
        line = data.decode("ascii").rstrip("\n")
        self.written.append(line)
        if self.drop_at is not None and len(self.written) == self.drop_at:
            self.drop_at = None
            raise TransportError("scripted: link dropped")
        if not self.pairs:
            raise AssertionError(f"unexpected request {line!r}")
        expected, replies = self.pairs.popleft()
        assert line == expected, f"sent {line!r}, expected {expected!r}"
        for r in replies:
            self._out += (r if isinstance(r, bytes) else r.encode("ascii")) + b"\n"
        # Unsolicited lines queued right after this reply.
        while self.pairs and self.pairs[0][0] is None:
            for r in self.pairs.popleft()[1]:
                self._out += (r if isinstance(r, bytes) else r.encode("ascii")) + b"\n"

    def read(self, max_bytes, timeout):
        if not self._open:
            raise TransportError("scripted: closed")
        data = bytes(self._out[:max_bytes])
        del self._out[:max_bytes]
        return data

    @property
    def done(self):
        return not self.pairs and not self._out
