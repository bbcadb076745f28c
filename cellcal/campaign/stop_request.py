"""The request to stop a campaign at its next safe point (a light module: the command
line sets it from a signal handler before the campaign's heavy modules are loaded)."""

from __future__ import annotations

import threading


class StopRequest(threading.Event):
    """A stop event that remembers why it was set (a signal's name, for the records)."""

    def __init__(self) -> None:
        super().__init__()
        self.reason = ""

    def request(self, reason: str) -> None:
        if not self.is_set():
            self.reason = reason
        self.set()
