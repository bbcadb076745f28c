"""systemd's notification protocol, for a ``Type=notify`` service (sd_notify(3)).

A notification is one datagram of ``KEY=value`` lines to the Unix socket named by
``$NOTIFY_SOCKET``; a name starting with ``@`` is in the abstract namespace. The service
sends ``READY=1`` once it serves, ``STATUS=`` lines for ``systemctl status``,
``WATCHDOG=1`` at least every ``$WATCHDOG_USEC`` / 2 while it is healthy, ``STOPPING=1``
and ``RELOADING=1``. Without ``$NOTIFY_SOCKET`` (not started by systemd) nothing is sent.

Written on the standard library: the protocol is one ``sendto``, and the libraries are
worse for it (``sdnotify`` mangles non-ASCII status text; ``systemd-python`` has no
wheels and needs libsystemd's headers to build).
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

__all__ = ["Notifier"]

log = logging.getLogger("cellcal.service.sdnotify")


class Notifier:
    """Notifications to systemd; every call is a no-op returning False when the
    service was not started with a notification socket, or when sending fails (logged
    once: a service never stops for its supervisor's sake)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        name = env.get("NOTIFY_SOCKET", "")
        self.address: str | bytes = "\0" + name[1:] if name.startswith("@") else name
        self.watchdog_s: float | None = None
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._warned = False

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to send ``WATCHDOG=1``: half the supervisor's timeout, or None when
        no watchdog is configured."""
        return None if self.watchdog_s is None else self.watchdog_s / 2

    def send(self, **fields: str | int) -> bool:
        """Send ``KEY=value`` lines at once (``send(READY=1, STATUS="idle")``). A value
        is one line: line breaks are folded into spaces."""
        if not self.address or not fields:
            return False
        text = "".join(f"{k}={' '.join(str(v).splitlines())}\n" for k, v in fields.items())
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                # Never block the service's loop on a supervisor that does not read.
                s.setblocking(False)
                s.sendto(text.encode("utf-8"), self.address)
        except OSError as exc:
            if not self._warned:
                log.warning("sd_notify to %s failed: %s", self.address, exc)
                self._warned = True
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.send(READY=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        return self.send(STATUS=text)

    def watchdog(self) -> bool:
        return self.send(WATCHDOG=1)

    def stopping(self, status: str = "") -> bool:
        return self.send(STOPPING=1, **({"STATUS": status} if status else {}))

    def reloading(self) -> bool:
        """``RELOADING=1`` with the monotonic clock systemd 253+ wants; ``ready()`` ends
        the reload."""
        return self.send(
            RELOADING=1, MONOTONIC_USEC=time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        )
