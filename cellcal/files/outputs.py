"""Writing the user's output files (``--out``, report folders, image sets) safely.

A file is written whole or not at all: into a new temporary file in the target's
folder (created exclusively, never through a link), then renamed over the target. A
target that exists and is not a regular file — a device (``/dev/full``), a FIFO, a
socket, a folder, or a symbolic link to one of them — is refused with one
:class:`~cellcal.errors.FileFormatError` line that names it, and left as it was: as
root a rename would replace the device node with an ordinary file. A symbolic link to a
regular file is replaced by the new file, as a rename does (the file it pointed to is
left alone: writing through a link another user planted would write where they chose).
"""

from __future__ import annotations

import errno
import os
import secrets
import stat
from pathlib import Path

from cellcal.errors import FileFormatError

_KINDS = {
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFIFO: "a FIFO",
    stat.S_IFSOCK: "a socket",
}


def check_output_file(path: str | Path) -> None:
    """Refuse ``path`` as an output file when it exists and is not a regular file (the
    check every writer makes before it writes, and a command may make before its work)."""
    p = Path(path)
    try:
        info = os.stat(p)  # through a symbolic link: what it points to
    except FileNotFoundError:
        return  # nothing there, or a dangling link (replaced, as a rename does)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise FileFormatError(f"{p}: a loop of symbolic links") from None
        if exc.errno == errno.ENOTDIR:
            raise FileFormatError(f"{p}: a part of the path is not a folder") from None
        raise FileFormatError(f"{p}: cannot write ({exc.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise FileFormatError(f"{p}: is a directory; give a file name")
    if not stat.S_ISREG(info.st_mode):
        kind = _KINDS.get(stat.S_IFMT(info.st_mode), "not a regular file")
        raise FileFormatError(
            f"{p}: {kind}, not a regular file; refused, nothing written (give a file name)"
        )


def _temporary(folder: Path, name: str) -> tuple[int, Path]:
    """A new file beside the target, created exclusively (never through a link), with
    the mode ``open()`` gives (0666 less the umask, applied by the system: no umask is
    changed, which other threads would see)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    for _ in range(100):
        tmp = folder / f".{name[:200]}.{secrets.token_hex(6)}.tmp"
        try:
            return os.open(tmp, flags, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(folder))


def write_atomically(path: str | Path, data: bytes | str, *, durable: bool = True) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` so that a reader sees the old file or
    the whole new one; an existing ``path`` that is not a regular file is refused.
    ``durable``: on the disk (fsync) before it replaces the old file."""
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise FileFormatError(f"{p}: folder {folder} does not exist")
    check_output_file(p)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    try:
        fd, tmp = _temporary(folder, p.name)
    except OSError as exc:
        raise FileFormatError(f"{p}: cannot write ({exc.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        check_output_file(p)  # not turned into a device or a folder meanwhile
        os.replace(tmp, p)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise FileFormatError(f"{p}: cannot write ({exc.strerror})") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
