"""Who may use what, across processes: advisory locks (``flock``) that the OS releases
when their holder dies, SIGKILL included. Each holder writes who it is into the lock
file, so a refusal names it.

- :class:`RunLock`: one process per database *file* (a ``cellcal run`` or the service),
  keyed on the file's identity (device and inode): every path to it — a hard link, a
  symbolic link, another folder's name for it — meets the same lock.
- :class:`RobotClaim`: one process per robot, whatever the database: two campaigns never
  drive one robot. The claim is keyed on where the driver connects — the address
  resolved to its IP addresses and port (``localhost``, ``127.1`` and ``0x7f000001`` are
  all 127.0.0.1; a UR controller on its RTDE port and its Modbus port alike, so that
  the ``ur`` and the ``modbus`` driver meet on one arm), or a device's node — never on
  how the address is spelled, and the driver then connects to the address the claim
  resolved (:attr:`RobotClaim.address`), not to the name resolved again. The claims
  live in ``/run/lock`` (``$CELLCAL_LOCK_DIR`` elsewhere), a folder every user may write
  and the service's unit leaves writable. A mock robot is the process's own twin:
  nothing to claim.

The lock folder is shared with every local user, so a lock file is opened without
following a symbolic link and must be a regular file with one link, ours or root's (or
a claim another user left open to all, as cellcal leaves them); anything else is
refused in one line and left as it was, and only a file this process created is
chmod'ed. What a holder wrote is shown as one printable line of bounded length, and
said to be what the holder wrote.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import re
import stat
from pathlib import Path

from cellcal.campaign.robot_endpoint import RobotEndpoint, robot_endpoint
from cellcal.config import CellConfig
from cellcal.errors import CampaignError

DEFAULT_LOCK_DIR = "/run/lock"
#: At most this many characters of what a holder wrote are shown.
MAX_SHOWN = 200
_KINDS = {
    stat.S_IFDIR: "a folder",
    stat.S_IFLNK: "a symbolic link",
    stat.S_IFIFO: "a FIFO",
    stat.S_IFSOCK: "a socket",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
}
_OPEN = os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC


def lock_dir() -> Path:
    return Path(os.environ.get("CELLCAL_LOCK_DIR") or DEFAULT_LOCK_DIR)


def shown_text(raw: bytes) -> str:
    """What a holder wrote, as it may be shown: its first line that is not blank, every
    character that does not print (escapes, bells, direction overrides) as ``?``, at most
    :data:`MAX_SHOWN` characters."""
    text = raw.decode("utf-8", errors="replace")
    line = next((x for x in text.splitlines() if x.strip()), "")
    clean = " ".join("".join(c if c.isprintable() else "?" for c in line).split())
    return clean if len(clean) <= MAX_SHOWN else clean[: MAX_SHOWN - 1] + "…"


def _refuse(path: str, why: str) -> CampaignError:
    return CampaignError(f"{path}: {why}; refused as a lock file, left as it is (remove it)")


def _check(path: str, info: os.stat_result) -> None:
    """Refuse a lock file that is not a regular file with one link, ours or root's (or
    open to every user, as cellcal leaves a claim for the next holder)."""
    if not stat.S_ISREG(info.st_mode):
        kind = _KINDS.get(stat.S_IFMT(info.st_mode), "not a regular file")
        raise _refuse(path, f"{kind}, not a regular file")
    if info.st_nlink != 1:
        raise _refuse(path, f"a file with {info.st_nlink} hard links")
    shared = stat.S_IMODE(info.st_mode) & 0o666 == 0o666
    if info.st_uid not in (os.geteuid(), 0) and not shared:
        raise _refuse(path, f"owned by uid {info.st_uid}, not by you or root")


def _open_or_create(path: str, shared: bool) -> int | None:
    """The existing file (never through a link), else a new one; None when another
    process created it in between."""
    with contextlib.suppress(FileNotFoundError):
        return os.open(path, _OPEN)
    try:
        fd = os.open(path, _OPEN | os.O_CREAT | os.O_EXCL, 0o666)
    except FileExistsError:
        return None
    if shared:  # ours, just created: open to the next holder, whatever the umask
        with contextlib.suppress(OSError):
            os.fchmod(fd, 0o666)
    return fd


def _open(path: str, shared: bool) -> int:
    """The lock file at ``path``, opened for reading and writing without following a
    link, or created (``shared``: readable and writable by every user)."""
    with contextlib.suppress(FileNotFoundError):
        _check(path, os.lstat(path))  # before opening: opening a device may act
    fd: int | None = None
    try:
        for _ in range(100):
            fd = _open_or_create(path, shared)
            if fd is not None:
                break
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _refuse(path, "a symbolic link") from None
        if exc.errno == errno.EISDIR:
            raise _refuse(path, "a folder, not a regular file") from None
        raise CampaignError(f"{path}: cannot open or create ({exc.strerror})") from None
    if fd is None:
        raise CampaignError(f"{path}: created and removed again and again; try again")
    try:
        _check(path, os.fstat(fd))
    except BaseException:
        os.close(fd)
        raise
    return fd


def _same_file(path: str, fd: int) -> bool:
    """Whether ``path`` still names the file open as ``fd`` (a holder that removes its
    lock file on release may have removed it between our open and our lock)."""
    try:
        now = os.lstat(path)
    except OSError:
        return False
    held = os.fstat(fd)
    return (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino)


class _Lock:
    """An exclusive, non-blocking ``flock`` on the lock file ``path``, held until
    ``__exit__``; ``remove``: the file is removed on release."""

    def __init__(
        self, path: str, holder: str, refusal: str, *, shared: bool = False, remove: bool = False
    ) -> None:
        self.path = path
        self.holder = holder
        self.refusal = refusal  # the refusal, to be followed by who holds the lock
        self.shared = shared
        self.remove = remove
        self.fd: int | None = None
        self.previous = ""  # what the last holder wrote (after a crash: who crashed)

    def __enter__(self) -> _Lock:
        for _ in range(20):
            fd = _open(self.path, self.shared)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                who = shown_text(os.pread(fd, 4096, 0))
                os.close(fd)
                if who:
                    who = f"{who} (as its holder wrote in {self.path})"
                else:
                    who = f"another cellcal process ({self.path})"
                raise CampaignError(f"{self.refusal} {who}") from None
            if _same_file(self.path, fd):
                break
            os.close(fd)  # removed or replaced by its last holder: take the new one
        else:
            raise CampaignError(f"{self.path}: replaced again and again while being locked")
        self.fd = fd
        self.previous = shown_text(os.pread(fd, 4096, 0))
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{self.holder} (pid {os.getpid()})\n".encode(), 0)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.fd is not None:
            if self.remove and _same_file(self.path, self.fd):
                with contextlib.suppress(OSError):  # another user's file in a sticky folder
                    os.unlink(self.path)
            os.close(self.fd)
            self.fd = None


def _slug(key: str) -> str:
    """``key`` as a file name's part: letters, digits, dots and dashes, and when another
    character had to be replaced (an IPv6 address's colons, a path's slashes) or the key
    is long, a hash of the whole key, so that two keys never share a name."""
    slug = re.sub(r"[^A-Za-z0-9.-]", "_", key)[:80]
    if slug != key:
        slug += "-" + hashlib.sha256(key.encode()).hexdigest()[:16]
    return slug


class RobotClaim:
    """One process per robot: ``cellcal-robot-<endpoint>.lock`` in the lock folder, one
    for each address the robot's host resolves to and each port the robot is reached
    on (``tcp-127.0.0.1-502``; a UR's ``tcp-127.0.0.1-30004`` and ``-502``), or for a
    device its node (``dev-188-0``). Once held, :attr:`address` is where the driver is
    to connect: the address the claim resolved."""

    def __init__(self, driver: str, address: str, holder: str) -> None:
        self.driver = driver
        self.configured = address
        self.holder = holder
        self.locks: list[_Lock] = []
        self.previous = ""
        self.endpoint: RobotEndpoint | None = None

    @property
    def address(self) -> str | None:
        """The robot's address for its driver, as the claim resolved it (None before
        the claim is held, or for a driver that takes its address as configured)."""
        return (self.endpoint.connect or None) if self.endpoint is not None else None

    @property
    def fd(self) -> int | None:
        return self.locks[0].fd if self.locks else None

    @property
    def paths(self) -> list[str]:
        return [lock.path for lock in self.locks]

    def __enter__(self) -> RobotClaim:
        folder = lock_dir()
        if not folder.is_dir():
            raise CampaignError(
                f"{folder}: no such folder for the robot claims (set CELLCAL_LOCK_DIR)"
            )
        endpoint = robot_endpoint(self.driver, self.configured)
        robot = f"the {self.driver} robot at {self.configured or 'its default address'}"
        if endpoint.shown and endpoint.shown != self.configured:
            robot += f" ({endpoint.shown})"
        refusal = robot + " is claimed by"
        try:
            for key in endpoint.keys:
                path = str(folder / f"cellcal-robot-{_slug(key)}.lock")
                lock = _Lock(path, self.holder, refusal, shared=True)
                lock.__enter__()
                self.locks.append(lock)
        except BaseException:
            self.__exit__()
            raise
        self.previous = next((lock.previous for lock in self.locks if lock.previous), "")
        self.endpoint = endpoint
        return self

    def __exit__(self, *exc: object) -> None:
        for lock in reversed(self.locks):
            lock.__exit__()
        self.locks = []
        self.endpoint = None


def _database(db_path: str) -> tuple[os.stat_result, bool]:
    """The database file (created empty when there is none, as SQLite would) and whether
    it was created here; a database that is not a regular file is refused."""
    created = False
    try:
        info = os.stat(db_path)
    except FileNotFoundError:
        target = os.path.realpath(db_path)  # a dangling symbolic link: where it points
        try:
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
        except FileExistsError:
            return _database(db_path)
        except OSError as exc:
            raise CampaignError(f"{db_path}: cannot create ({exc.strerror})") from None
        info = os.fstat(fd)
        os.close(fd)  # a file no SQLite connection of this process has open yet
        created = True
    except OSError as exc:
        raise CampaignError(f"{db_path}: cannot open ({exc.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise CampaignError(f"{db_path}: is a directory, not a database")
    if not stat.S_ISREG(info.st_mode):
        raise CampaignError(f"{db_path}: not a regular file (a device, FIFO or socket)")
    return info, created


def _identity(db_path: str) -> tuple[int, int] | None:
    try:
        info = os.stat(db_path)
    except OSError:
        return None
    return info.st_dev, info.st_ino


def _identity_lock(db_path: str, key: tuple[int, int]) -> str:
    """The lock named by a database's identity: in the lock folder, which every path to
    the file shares; where there is none to write, hidden in the database's own folder."""
    name = f"cellcal-db-{key[0]}-{key[1]}.lock"
    folder = lock_dir()
    if folder.is_dir() and os.access(folder, os.W_OK | os.X_OK):
        return str(folder / name)
    return str(Path(os.path.realpath(db_path)).parent / f".{name}")


class RunLock:
    """One process per database file: ``cellcal-db-<device>-<inode>.lock`` in the lock
    folder (removed on release), and ``<db>.lock`` beside the database, which keeps who
    held it last (after a crash: who crashed) and meets another host's lock on a shared
    folder."""

    def __init__(self, db_path: str, holder: str = "cellcal run") -> None:
        self.db_path = str(db_path)
        self.holder = holder
        self.previous = ""
        self.locks: list[_Lock] = []
        self._created: tuple[int, int] | None = None

    @property
    def fd(self) -> int | None:
        return self.locks[-1].fd if self.locks else None

    def __enter__(self) -> RunLock:
        db = self.db_path
        refusal = f"{db}: this database is in use by"
        info, created = _database(db)
        self._created = (info.st_dev, info.st_ino) if created else None
        try:
            for _ in range(20):
                key = (info.st_dev, info.st_ino)
                path = _identity_lock(db, key)
                lock = _Lock(path, self.holder, refusal, shared=True, remove=True)
                lock.__enter__()
                if _identity(db) == key:
                    break
                lock.__exit__()  # another file was moved to this path meanwhile
                info = _database(db)[0]
            else:
                raise CampaignError(f"{db}: replaced again and again while being locked")
            self.locks.append(lock)
            beside = _Lock(f"{os.path.realpath(db)}.lock", self.holder, refusal)
            beside.__enter__()
            self.locks.append(beside)
        except BaseException:
            self.__exit__()
            raise
        self.previous = beside.previous
        return self

    def __exit__(self, *exc: object) -> None:
        if self._created is not None:
            self._remove_if_unused()
            self._created = None
        for lock in reversed(self.locks):
            lock.__exit__()
        self.locks = []

    def _remove_if_unused(self) -> None:
        """The empty database this lock created, when nothing was written to it."""
        db = self.db_path
        with contextlib.suppress(OSError):
            info = os.stat(db)
            unused = info.st_size == 0 and not any(
                os.path.lexists(f"{db}{suffix}") for suffix in ("-wal", "-journal")
            )
            if unused and (info.st_dev, info.st_ino) == self._created:
                os.unlink(os.path.realpath(db))


def robot_claim(
    config: CellConfig, holder: str, *, needed: bool
) -> contextlib.AbstractContextManager[RobotClaim | None]:
    """The claim on the configuration's robot when ``needed``: not in mock mode (the
    twin is the process's own), nor on devices a caller holds (and has claimed). It
    gives the claim held (None when not needed): :func:`claimed_address` of it is where
    the driver connects."""
    if not needed:
        return contextlib.nullcontext()
    return RobotClaim(config.robot.driver, config.robot.address, holder)


def claimed_address(claim: RobotClaim | None) -> str | None:
    """Where the claimed robot's driver connects (``build_devices(robot_address=…)``):
    the address its claim resolved; None without a claim (mock mode, devices held)."""
    return claim.address if claim is not None else None
