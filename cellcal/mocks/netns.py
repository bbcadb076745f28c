"""A private network namespace for one thread, with 127.0.0.2.. on its loopback.

The GigE Vision twin's fake cameras each need their own address on an interface (GVCP's
port 3956 is fixed), and nothing of that must show in the host's network. Linux
namespaces belong to a *thread*: ``unshare(CLONE_NEWNET)`` moves only the calling thread,
and the threads and processes it starts afterwards inherit the new namespace. So
:func:`run_in_new_netns` starts a thread, moves it into a fresh namespace, brings ``lo``
up with the addresses (ioctls on a socket of that namespace, no ``ip`` binary), runs the
given function there and returns what it returned together with a path by which other
threads can join the namespace (``setns``). The rest of the process (other twins on
127.0.0.x, the engine) stays where it was.

Making a network namespace needs ``CAP_SYS_ADMIN``: root has it; an unprivileged user
gets it by running the whole program as ``unshare -r <command>`` (root mapped in a user
namespace of its own; the host's network is still the one the process uses), where user
namespaces are allowed. Anything else raises :class:`NamespaceUnavailableError` with one
line saying so.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import shutil
import socket
import struct
import subprocess
import threading
from collections.abc import Callable, Sequence
from typing import TypeVar

from cellcal.errors import DeviceError

__all__ = ["NamespaceUnavailableError", "loopback_addresses", "run_in_new_netns"]

T = TypeVar("T")

CLONE_NEWNET = 0x40000000
_SIOCGIFFLAGS, _SIOCSIFFLAGS, _SIOCSIFADDR = 0x8913, 0x8914, 0x8916
_IFF_UP = 0x1
_IFREQ_FLAGS = "16sH22x"  # struct ifreq: name, short flags, padding to 40 bytes
_IFREQ_ADDR = "16s16s8x"  # struct ifreq: name, struct sockaddr_in, padding

_libc = ctypes.CDLL(None, use_errno=True)
_libc.unshare.argtypes = [ctypes.c_int]
_libc.unshare.restype = ctypes.c_int


class NamespaceUnavailableError(DeviceError):
    """No network namespace can be made here (not root, user namespaces disabled)."""


def loopback_addresses(n: int, first: int = 2) -> tuple[str, ...]:
    """127.0.0.first, 127.0.0.first+1, ... (n of them)."""
    if n < 0 or first < 2 or first + n > 255:
        raise ValueError(f"loopback addresses: {n} from 127.0.0.{first} do not fit")
    return tuple(f"127.0.0.{first + i}" for i in range(n))


def _userns_works() -> bool:
    """Whether ``unshare -r`` works here (user namespaces allowed for this user)."""
    tool = shutil.which("unshare")
    if tool is None:
        return False
    try:
        done = subprocess.run([tool, "-r", "true"], capture_output=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _why_not(errno: int) -> str:
    what = f"cannot make a network namespace for the camera twin ({os.strerror(errno)})"
    if os.geteuid() == 0:
        return f"{what}: the kernel or a container forbids it"
    if _userns_works():
        return f"{what}: run as root, or as `unshare -r <command>` (user namespaces work here)"
    return f"{what}: run as root (user namespaces are disabled here)"


def _unshare_net() -> None:
    if _libc.unshare(CLONE_NEWNET) != 0:
        raise NamespaceUnavailableError(_why_not(ctypes.get_errno()))


def _configure_loopback(addresses: Sequence[str]) -> None:
    """``lo`` up, and each address as an alias ``lo:N`` (/8), in this thread's namespace."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        raw = fcntl.ioctl(s, _SIOCGIFFLAGS, struct.pack(_IFREQ_FLAGS, b"lo", 0))
        flags = struct.unpack(_IFREQ_FLAGS, raw)[1]
        fcntl.ioctl(s, _SIOCSIFFLAGS, struct.pack(_IFREQ_FLAGS, b"lo", flags | _IFF_UP))
        for address in addresses:
            packed = socket.inet_aton(address)
            sockaddr = struct.pack("=H2s4s8x", socket.AF_INET, b"\0\0", packed)
            alias = f"lo:{packed[3]}".encode()
            fcntl.ioctl(s, _SIOCSIFADDR, struct.pack(_IFREQ_ADDR, alias, sockaddr))


def run_in_new_netns(addresses: Sequence[str], fn: Callable[[], T]) -> tuple[T, int]:
    """Run ``fn`` in a new thread inside a fresh network namespace whose ``lo`` is up
    with ``addresses``; return ``fn``'s result and a file descriptor of the namespace
    (``/proc/<pid>/fd/<fd>`` joins it with ``setns``; close it when done). Threads that
    ``fn`` starts stay in the namespace. Raises :class:`NamespaceUnavailableError`, or
    what ``fn`` raised."""
    out: dict[str, object] = {}

    def body() -> None:
        try:
            _unshare_net()
            _configure_loopback(addresses)
            out["fd"] = os.open("/proc/thread-self/ns/net", os.O_RDONLY | os.O_CLOEXEC)
            out["result"] = fn()
        except BaseException as exc:  # handed to the caller's thread below
            out["error"] = exc

    thread = threading.Thread(target=body, name="netns", daemon=True)
    thread.start()
    thread.join()
    error = out.get("error")
    if error is not None:
        if "fd" in out:
            os.close(out["fd"])  # type: ignore[arg-type]
        raise error  # type: ignore[misc]
    return out["result"], out["fd"]  # type: ignore[return-value]
