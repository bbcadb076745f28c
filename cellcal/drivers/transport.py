"""Byte transports chosen by a pyserial URL: one code path for a serial line, a
pseudo-terminal and TCP (``/dev/ttyUSB0``, ``/dev/pts/7``, ``socket://127.0.0.5:5555``).

A transport moves bytes and reports a broken link as :class:`TransportError`; the
layers above (line framing, protocol) know nothing of sockets or serial ports.

Only plain transports are taken: a serial device (a path to a character device),
``socket://`` and ``rfc2217://``. pyserial's other URL handlers are refused before
anything is opened (:class:`RefusedAddressError`): ``spy://…?file=`` opens a file for
writing (and empties it), ``hwgrep://`` opens whichever port matches a pattern,
``alt://`` swaps the port's implementation, ``loop://`` and ``cp2110://`` are no serial
line to a tracker.
"""

from __future__ import annotations

import contextlib
import os
import stat
import time
from typing import Protocol

import serial

from cellcal.errors import DeviceError, InputError


class TransportError(DeviceError):
    """The link is down: a dropped connection, an unplugged device, a refused connect."""


class RefusedAddressError(InputError):
    """An address that is no plain transport: a pyserial URL handler that writes files
    or is not a serial line or TCP, or a path that is not a serial device."""


#: The pyserial URL kinds taken: plain TCP and RFC 2217 (a serial port over telnet).
PLAIN_SCHEMES = ("socket", "rfc2217")

_WHY = {
    "spy": "it writes a log of the traffic into a file (file=...) and wraps another port",
    "hwgrep": "it opens whichever serial port matches a pattern",
    "alt": "it swaps the serial port's implementation",
    "loop": "it is a loopback, no device",
    "cp2110": "it is a USB HID bridge, not a serial line",
}


def check_address(url: str) -> None:
    """Refuse a pyserial URL that is not a plain transport (see the module's docstring)."""
    scheme, sep, _ = url.partition("://")
    if not sep:
        return
    scheme = scheme.lower()  # as pyserial reads it
    if scheme in PLAIN_SCHEMES:
        return
    why = _WHY.get(scheme, "it is not a serial or TCP transport")
    raise RefusedAddressError(
        f"{url}: {scheme}:// addresses are refused ({why}); give a serial device "
        "(/dev/ttyUSB0, a pty path), socket://HOST:PORT or rfc2217://HOST:PORT"
    )


def _check_device(url: str) -> None:
    """A path (no URL kind) must be a character device when it exists: pyserial would
    open a regular file, a FIFO or a folder for reading and writing."""
    if "://" in url:
        return
    try:
        info = os.stat(url)
    except OSError:
        return  # not there (unplugged?): pyserial says so, and the link layer retries
    if not stat.S_ISCHR(info.st_mode):
        raise RefusedAddressError(
            f"{url}: not a serial device (not a character device); give a serial device "
            "(/dev/ttyUSB0, a pty path), socket://HOST:PORT or rfc2217://HOST:PORT"
        )


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


#: At most this many bytes are taken from the port at once: whatever has arrived, after
#: the first byte was waited for; what a caller did not ask for waits in the transport.
CHUNK = 4096
#: A wait for the first byte is cut into slices of at most this long (s).
SLICE_S = 0.05


class SerialUrlTransport:
    """A pyserial ``serial_for_url`` port (serial device, pty path, ``socket://`` or
    ``rfc2217://``); any other URL kind is refused here, before anything is opened.

    A read waits for the first byte (in slices of :data:`SLICE_S`, until its timeout),
    then takes without waiting whatever else has arrived, up to :data:`CHUNK` bytes, and
    keeps what the caller did not ask for for the next read: two calls to the port for a
    burst of bytes, where pyserial's ``socket://`` port, whose ``in_waiting`` says only
    whether something waits, gave one byte a call."""

    def __init__(self, url: str, *, baudrate: int = 115200, connect_timeout: float = 5.0) -> None:
        check_address(url)
        self.url = url
        self.baudrate = baudrate
        self.connect_timeout = connect_timeout
        self._port: serial.SerialBase | None = None
        self._pending = bytearray()  # received, not yet read

    @property
    def is_open(self) -> bool:
        return self._port is not None and bool(self._port.is_open)

    def open(self) -> None:
        self.close()
        check_address(self.url)
        _check_device(self.url)
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=SLICE_S,
                write_timeout=self.connect_timeout,
                do_not_open=True,
            )
            port.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"{self.url}: cannot open ({exc})") from None
        self._port = port

    def close(self) -> None:
        self._pending.clear()  # what came before a reconnect is not the new link's
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
        port = self._port
        if port is None:
            raise TransportError(f"{self.url}: not open")
        if not self._pending:
            deadline = time.monotonic() + max(timeout, 0.0)
            try:
                while True:
                    port.timeout = max(0.0, min(SLICE_S, deadline - time.monotonic()))
                    first = bytes(port.read(1))
                    if first:
                        break
                    if time.monotonic() >= deadline:
                        return b""
            except (serial.SerialException, OSError) as exc:
                raise TransportError(f"{self.url}: connection lost ({exc})") from None
            self._pending += first
            # The rest of what has arrived, without waiting; a link lost after these
            # bytes: they are read, and the next read says it is lost.
            with contextlib.suppress(serial.SerialException, OSError):
                port.timeout = 0
                self._pending += port.read(CHUNK - 1)
        n = max(1, max_bytes)
        data = bytes(self._pending[:n])
        del self._pending[:n]
        return data
