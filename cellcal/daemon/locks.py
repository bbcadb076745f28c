"""Who may use what, across processes: advisory locks (``flock``) that the OS releases
when their holder dies, SIGKILL included. Each holder writes who it is into the lock
file, so a refusal names it.

- :class:`RunLock`: one process per database file (a ``cellcal run`` or the service).
- :class:`RobotClaim`: one process per robot (its driver and address), whatever the
  database: two campaigns never drive one robot. The claims live in ``/run/lock``
  (``$CELLCAL_LOCK_DIR`` elsewhere), a folder every user may write and the service's
  unit leaves writable. A mock robot is the process's own twin: nothing to claim.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
from pathlib import Path

from cellcal.config import CellConfig
from cellcal.errors import CampaignError

DEFAULT_LOCK_DIR = "/run/lock"


class _Lock:
    """An exclusive, non-blocking ``flock`` on ``path``, held until ``__exit__``."""

    def __init__(self, path: str, holder: str, refusal: str) -> None:
        self.path = path
        self.holder = holder
        self.refusal = refusal  # the refusal, with {who} for the holder
        self.fd: int | None = None
        self.previous = ""  # what the last holder wrote (after a crash: who crashed)

    def __enter__(self) -> _Lock:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise CampaignError(f"{self.path}: cannot create ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            who = os.pread(fd, 4096, 0).decode(errors="replace").strip()
            os.close(fd)
            who = who or "another cellcal process"
            raise CampaignError(self.refusal.format(who=who, path=self.path)) from None
        self.fd = fd
        self.previous = os.pread(fd, 4096, 0).decode(errors="replace").strip()
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{self.holder} (pid {os.getpid()})\n".encode(), 0)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


class RunLock(_Lock):
    """One process per database file: ``<db>.lock``."""

    def __init__(self, db_path: str, holder: str = "cellcal run") -> None:
        super().__init__(f"{db_path}.lock", holder, "{path}: this database is in use by {who}")

    def __enter__(self) -> RunLock:
        super().__enter__()
        return self


def lock_dir() -> Path:
    return Path(os.environ.get("CELLCAL_LOCK_DIR") or DEFAULT_LOCK_DIR)


class RobotClaim(_Lock):
    """One process per robot: ``cellcal-robot-<driver>-<address>.lock`` in the lock folder."""

    def __init__(self, driver: str, address: str, holder: str) -> None:
        slug = re.sub(r"[^A-Za-z0-9.-]+", "_", f"{driver}-{address}")
        robot = f"the {driver} robot at {address or 'its default address'}"
        path = str(lock_dir() / f"cellcal-robot-{slug}.lock")
        super().__init__(path, holder, robot + " is claimed by {who} ({path})")

    def __enter__(self) -> RobotClaim:
        folder = Path(self.path).parent
        if not folder.is_dir():
            raise CampaignError(
                f"{folder}: no such folder for the robot claims (set CELLCAL_LOCK_DIR)"
            )
        super().__enter__()
        with contextlib.suppress(OSError):  # the next holder may be another user
            os.fchmod(self.fd if self.fd is not None else -1, 0o666)
        return self


def robot_claim(
    config: CellConfig, holder: str, *, needed: bool
) -> contextlib.AbstractContextManager[object]:
    """The claim on the configuration's robot when ``needed``: not in mock mode (the
    twin is the process's own), nor on devices a caller holds (and has claimed)."""
    if not needed:
        return contextlib.nullcontext()
    return RobotClaim(config.robot.driver, config.robot.address, holder)
