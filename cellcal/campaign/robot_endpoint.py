"""Where a robot driver connects, in one canonical form: what its claim is keyed on.

The same controller has many spellings: ``localhost``, ``127.1``, ``0x7f000001``,
``2130706433``, ``0177.0.0.1``, ``[::ffff:127.0.0.1]`` and ``127.0.0.1:502`` with the
driver's default port are all the Modbus server at 127.0.0.1 port 502, because the
driver hands the text to the system's resolver. So the address is resolved the same way
(``getaddrinfo``), each resolved address put in canonical form (an IPv4-mapped IPv6
address as IPv4; the unspecified address, which connects to this host, as loopback)
with its port. A serial device is its node (major:minor) whatever the path to it (a
``/dev/serial/by-id`` link, a symlink of one's own).

A robot is one robot however cellcal reaches it: a UR controller through ur_rtde (its
RTDE port) or through its Modbus TCP server (the ``modbus`` driver, port 502) is one
claim (:data:`SAME_ROBOT_PORTS`). And the driver connects to the address the claim was
resolved to (:attr:`RobotEndpoint.connect`), never resolves the name a second time: a
name that resolved otherwise meanwhile would reach a machine nobody claimed.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import stat
from dataclasses import dataclass
from urllib.parse import urlsplit

from cellcal.drivers.base import host_port
from cellcal.errors import CampaignError

#: The port each robot driver connects to when the address names none. A UR
#: controller's ports are fixed (RTDE 30004, dashboard 29999, script 30003): its claim
#: is its host at the RTDE port.
DEFAULT_PORTS = {"modbus": 502, "ur": 30004}
#: The other ports of a driver's robot that its claim covers: a UR controller serves
#: Modbus TCP on 502 too, which the ``modbus`` driver reaches (its default port), so the
#: same arm configured with either driver is one claim.
SAME_ROBOT_PORTS = {"ur": (502,)}


@dataclass(frozen=True)
class RobotEndpoint:
    """A robot's endpoint: ``keys`` (one per resolved address and port the robot is
    reached on, or the device's node), ``shown``, the canonical form for messages
    (``127.0.0.1:502``), and ``connect``: the address its driver is to connect to, the
    one the host resolved to first, in the driver's form (``127.0.0.1:502``, a UR's
    host alone; "" where the driver takes the address as configured: a device, a URL)."""

    keys: tuple[str, ...]
    shown: str
    connect: str = ""


def _canonical(ip: str) -> str:
    text, _, scope = ip.partition("%")
    addr: ipaddress.IPv4Address | ipaddress.IPv6Address = ipaddress.ip_address(text)
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        addr = addr.ipv4_mapped
    if addr.is_unspecified:  # connecting to 0.0.0.0 or :: reaches this host
        addr = ipaddress.ip_address("127.0.0.1" if addr.version == 4 else "::1")
    out = str(addr)
    return f"{out}%{scope}" if scope and addr.version == 6 else out


def _address(sockaddr: tuple[object, ...]) -> str:
    """The IP address of a ``getaddrinfo`` socket address, an IPv6 one with its scope
    (the interface of a link-local address) by number."""
    ip = str(sockaddr[0]).partition("%")[0]
    scope = sockaddr[3] if len(sockaddr) == 4 else 0
    return f"{ip}%{scope}" if scope else ip


def _device(path: str) -> RobotEndpoint:
    real = os.path.realpath(path)
    try:
        info = os.stat(path)
    except OSError:  # not there (unplugged): its path, as the system names it
        return RobotEndpoint((f"path-{real}",), real)
    if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode):
        major, minor = os.major(info.st_rdev), os.minor(info.st_rdev)
        return RobotEndpoint((f"dev-{major}-{minor}",), f"{real} (device {major}:{minor})")
    return RobotEndpoint((f"file-{info.st_dev}-{info.st_ino}",), real)


def robot_endpoint(driver: str, address: str) -> RobotEndpoint:
    """The endpoint of the ``driver``'s robot at ``address`` (host, host:port, a URL or a
    device path); a host that does not resolve is a :class:`CampaignError`."""
    if not address:
        return RobotEndpoint((f"{driver}-default",), "")
    if address.startswith("/"):
        return _device(address)
    default = DEFAULT_PORTS.get(driver, 0)
    try:
        if "://" in address:
            parts = urlsplit(address)
            host, port = parts.hostname or "", parts.port or default
        else:
            host, port = host_port(address, default)
    except ValueError as exc:
        raise CampaignError(f"robot.address {address!r}: {exc}") from None
    if not 0 <= port <= 0xFFFF:
        raise CampaignError(f"robot.address {address!r}: port {port} is not 0..65535")
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        raise CampaignError(
            f"robot.address {address!r}: cannot resolve {host!r} ({why}); the robot's "
            "claim is keyed on the address it resolves to"
        ) from None
    first = _canonical(_address(found[0][4])) if found else ""
    ips = sorted({_canonical(_address(info[4])) for info in found})
    shown = ", ".join(_joined(ip, port) for ip in ips)
    ports = (port, *(p for p in SAME_ROBOT_PORTS.get(driver, ()) if p != port))
    keys = tuple(f"tcp-{ip}-{p}" for ip in ips for p in ports)
    if "://" in address or not first or driver not in DEFAULT_PORTS:
        return RobotEndpoint(keys, shown)  # a driver whose address form is not known
    return RobotEndpoint(keys, shown, first if driver == "ur" else _joined(first, port))


def _joined(ip: str, port: int) -> str:
    """``ip:port``, an IPv6 address in brackets."""
    return f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}"
