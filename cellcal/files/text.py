"""Reading the user's text files at the edge, bounded and with one clear line per fault.

A measurement CSV, a model or a configuration is a regular UTF-8 file of sane size.
``/dev/zero``, ``/dev/urandom``, a FIFO (which would block forever), a symlink loop, a
file the user may not read, a directory, or a file larger than :data:`MAX_BYTES` is
refused with a :class:`~cellcal.errors.FileFormatError` that names the file — never a
hang, a MemoryError or a traceback. TOML is parsed here too, with deep nesting (which
makes the standard parser recurse) refused the same way.
"""

from __future__ import annotations

import errno
import os
import stat
import tomllib
from pathlib import Path
from typing import Any

from cellcal.errors import FileFormatError

#: Larger files are refused: 10⁶ measurement rows are about 80 MB.
MAX_BYTES = 256 * 1024 * 1024


def read_text(path: str | Path, kind: str, *, limit: int = MAX_BYTES) -> str:
    """The text of ``path`` (UTF-8, a BOM dropped); ``kind`` names the expected file in
    messages ("a CSV file", "a TOML file")."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise FileFormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise FileFormatError(f"{p}: is a directory, not {kind}") from None
    except PermissionError:
        raise FileFormatError(f"{p}: cannot be read (permission denied)") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FileFormatError(f"{p}: a loop of symbolic links") from None
        raise FileFormatError(f"{p}: cannot be read ({exc.strerror})") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise FileFormatError(f"{p}: is a directory, not {kind}")
        if not stat.S_ISREG(info.st_mode):
            raise FileFormatError(f"{p}: not a regular file (a device, FIFO or socket), not {kind}")
        if info.st_size > limit:
            raise FileFormatError(
                f"{p}: {info.st_size / 1e6:.0f} MB is too large for {kind} "
                f"(at most {limit / 1e6:.0f} MB)"
            )
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=True) as fh:
            fd = -1
            raw = fh.read(limit + 1)
    except OSError as exc:
        raise FileFormatError(f"{p}: cannot be read ({exc.strerror})") from None
    finally:
        if fd >= 0:
            os.close(fd)
    if len(raw) > limit:
        raise FileFormatError(f"{p}: too large for {kind} (grew while read)")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise FileFormatError(f"{p}: not a UTF-8 text file") from None


def read_toml(path: str | Path, *, label: str | None = None) -> dict[str, Any]:
    """Parse a TOML file, every fault one FileFormatError naming ``label`` (or the path)."""
    name = label or str(path)
    text = read_text(path, "a TOML file")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FileFormatError(f"{name}: not valid TOML ({exc})") from None
    except RecursionError:
        raise FileFormatError(f"{name}: nested too deeply to be a cellcal file") from None
