"""The emScon driver's link: one TCP connection to the tracker's TPI server, packets
read whole and checked (``emscon_packets.py``), and each command's reply found among
whatever the tracker sends meanwhile — status changes, reflector positions and errors it
sends on its own are kept as events, never taken for the reply.

Every failure is one :class:`~cellcal.errors.DeviceError` line naming the tracker: the
connection refused or dropped, a reply late, a packet that is not the protocol's (the
link is closed: a stream out of step cannot be trusted), a command the tracker refuses
(its status in words), another client already connected (one client only).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import time
from dataclasses import dataclass, field

from cellcal.drivers import emscon_packets as p
from cellcal.errors import DeviceError

log = logging.getLogger("cellcal.drivers.emscon")

DEFAULT_PORT = 700


class EmsconStatusError(DeviceError):
    """A command the tracker answered with a status other than OK."""

    def __init__(self, message: str, command: int, status: int, device: str | None = None):
        super().__init__(message, device=device)
        self.command = command
        self.status = status


@dataclass
class Events:
    """What the tracker sent on its own, in order: (monotonic time, packet)."""

    seen: list[tuple[float, p.Packet]] = field(default_factory=list)

    def add(self, packet: p.Packet) -> None:
        self.seen.append((time.monotonic(), packet))
        del self.seen[:-1000]  # a long campaign's events do not pile up

    def since(self, mark: int) -> list[p.Packet]:
        return [packet for _, packet in self.seen[mark:]]

    @property
    def mark(self) -> int:
        return len(self.seen)


class EmsconLink:
    """One connection; ``where`` names the tracker in every message ("tracker at host")."""

    def __init__(self, where: str, host: str, port: int, timeout_s: float) -> None:
        self.where = where
        self.host, self.port = host, port
        self.timeout_s = timeout_s
        self.sock: socket.socket | None = None
        self.events = Events()
        self._buf = b""

    def open(self) -> None:
        self.close()
        try:
            self.sock = socket.create_connection((self.host, self.port), self.timeout_s)
        except OSError as exc:
            why = exc.strerror or str(exc) or type(exc).__name__
            raise DeviceError(f"{self.where}: cannot connect ({why})") from None
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = b""

    def close(self) -> None:
        if self.sock is not None:
            with contextlib.suppress(OSError):
                self.sock.close()
            self.sock = None

    # -- bytes

    def _recv(self, deadline: float, waiting: str) -> None:
        if self.sock is None:
            raise DeviceError(f"{self.where}: not connected")
        left = deadline - time.monotonic()
        if left <= 0:
            raise DeviceError(f"{self.where}: no answer {waiting} within {self.timeout_s:g} s")
        self.sock.settimeout(left)
        try:
            chunk = self.sock.recv(65536)
        except TimeoutError:
            raise DeviceError(
                f"{self.where}: no answer {waiting} within {self.timeout_s:g} s"
            ) from None
        except OSError as exc:
            self.close()
            raise DeviceError(f"{self.where}: connection lost {waiting} ({exc})") from None
        if not chunk:
            self.close()
            raise DeviceError(f"{self.where}: the tracker closed the connection {waiting}")
        self._buf += chunk

    def read_packet(self, deadline: float, waiting: str) -> p.Packet:
        """The next whole packet; a DeviceError (the link closed) when its bytes are not
        the protocol's."""
        while len(self._buf) < p.HEADER.size:
            self._recv(deadline, waiting)
        try:
            size, _ = p.packet_size(self._buf[: p.HEADER.size])
            while len(self._buf) < size:
                self._recv(deadline, waiting)
            data, self._buf = self._buf[:size], self._buf[size:]
            return p.decode_packet(data)
        except p.PacketError as exc:
            head = self._buf[:16].hex(" ")
            self.close()
            raise DeviceError(
                f"{self.where}: {exc} {waiting}; not the emScon protocol (first bytes "
                f"{head}): is the address the tracker's TPI port?"
            ) from None

    def send(self, command: int, *params: object) -> None:
        if self.sock is None:
            raise DeviceError(f"{self.where}: not connected")
        data = p.encode_command(command, *params)
        try:
            self.sock.sendall(data)
        except OSError as exc:
            self.close()
            name = p.LAYOUTS[command].name
            raise DeviceError(f"{self.where}: connection lost sending {name} ({exc})") from None

    # -- commands

    def refused(self, command: int, status: int) -> EmsconStatusError:
        name = p.LAYOUTS[command].name if command in p.LAYOUTS else f"command {command}"
        if status == p.MULTI_CONNECTIONS_NOT_ALLOWED:
            return EmsconStatusError(
                f"{self.where}: another client is connected (the tracker serves one): close "
                "it (LMF, Tracker Pilot, another cellcal) and retry",
                command,
                status,
            )
        return EmsconStatusError(
            f"{self.where}: {name} refused: {p.status_text(status)} ({status})", command, status
        )

    def request(self, command: int, *params: object, timeout_s: float | None = None) -> p.Reply:
        """Send a command and return its reply (OK); :class:`EmsconStatusError` when the
        tracker refuses it, a DeviceError when no reply comes in time."""
        self.send(command, *params)
        return self.reply(command, timeout_s=timeout_s)

    def reply(self, command: int, *, timeout_s: float | None = None) -> p.Reply:
        name = p.LAYOUTS[command].name
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        waiting = f"to {name}"
        while True:
            packet = self.read_packet(deadline, waiting)
            if isinstance(packet, p.Reply) and packet.command == command:
                if packet.status != p.OK:
                    raise self.refused(command, packet.status)
                return packet
            # an error for no command (0) is the tracker's unsolicited news — a beam lost
            # while idle — not this command's answer, which still comes; one client too many
            # is the exception
            if isinstance(packet, p.ErrorPacket) and (
                packet.command == command or packet.status == p.MULTI_CONNECTIONS_NOT_ALLOWED
            ):
                raise self.refused(command, packet.status)
            self.note(packet, waiting)

    def note(self, packet: p.Packet, waiting: str) -> None:
        """A packet that is not what is waited for: an event, kept."""
        self.events.add(packet)
        log.debug("%s: %r while waiting %s", self.where, packet, waiting)
