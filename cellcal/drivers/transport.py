"""Byte transports chosen by a pyserial URL: one code path for a serial line, a
pseudo-terminal and TCP (``/dev/ttyUSB0``, ``/dev/pts/7``, ``socket://127.0.0.5:5555``).

A transport moves bytes and reports a broken link as :class:`TransportError`; the
layers above (line framing, protocol) know nothing of sockets or serial ports.
"""

from __future__ import annotations

import contextlib
import time
from typing import Protocol

import serial

from cellcal.errors import DeviceError


class TransportError(DeviceError):
    """The link is down: a dropped connection, an unplugged device, a refused connect."""


class Transport(Protocol):
    url: str

    def open(self) -> None: ...

    def close(self) -> None: ...

    @property
    def is_open(self) -> bool: ...

    def write(self, data: bytes) -> None: ...

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Up to ``max_bytes``; ``b""`` when nothing arrived within ``timeout`` seconds."""
        ...


class SerialUrlTransport:
    """A pyserial ``serial_for_url`` port (serial device, pty path or ``socket://``)."""

    def __init__(self, url: str, *, baudrate: int = 115200, connect_timeout: float = 5.0) -> None:
        self.url = url
        self.baudrate = baudrate
        self.connect_timeout = connect_timeout
        self._port: serial.SerialBase | None = None

    @property
    def is_open(self) -> bool:
        return self._port is not None and bool(self._port.is_open)

    def open(self) -> None:
        self.close()
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=0.05,
                write_timeout=self.connect_timeout,
                do_not_open=True,
            )
            port.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"{self.url}: cannot open ({exc})") from None
        self._port = port

    def close(self) -> None:
        if self._port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._port.close()
            self._port = None

    def write(self, data: bytes) -> None:
        if self._port is None:
            raise TransportError(f"{self.url}: not open")
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"{self.url}: write failed ({exc})") from None

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self._port is None:
            raise TransportError(f"{self.url}: not open")
        deadline = time.monotonic() + max(timeout, 0.0)
        try:
            while True:
                self._port.timeout = max(0.0, min(0.05, deadline - time.monotonic()))
                waiting = max(1, min(max_bytes, self._port.in_waiting or 1))
                data = bytes(self._port.read(waiting))
                if data:
                    return data
                if time.monotonic() >= deadline:
                    return b""
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"{self.url}: connection lost ({exc})") from None
