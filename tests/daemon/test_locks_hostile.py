"""The locks against hostile spellings and planted files (issue 29).

- A robot's claim is keyed on where the driver connects (the resolved IP address and
  port; a device's node), never on how the address is spelled.
- Lock files are opened without following a symbolic link; a lock path that is not a
  plain regular file of ours (a symlink, a FIFO, a hard link, another user's private
  file) is refused in one line and left as it was; what we did not create is never
  chmod'ed.
- What a holder wrote is shown sanitised: one printable line, bounded, and said to be
  what the holder wrote.
- The run lock is keyed on the database file's identity: every path to one file (a hard
  link, a symbolic link, in any folder) meets the same lock.
"""

from __future__ import annotations

import fcntl
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellcal.campaign.locks import RobotClaim, RunLock
from cellcal.cli import main
from cellcal.errors import CampaignError

#: Other spellings of 127.0.0.1 port 502 that the resolver (and so the driver) takes.
SPELLINGS = [
    "localhost:502",
    "LOCALHOST",
    "127.1:502",
    "127.0.1",
    "0x7f000001:502",
    "2130706433:502",
    "0177.0.0.1:502",
    "127.000.000.001:0502",
    "017700000001",
    "[::ffff:127.0.0.1]:502",
    "0.0.0.0:502",
    "127.0.0.1",
]


def _held_elsewhere(path: Path) -> Iterator[int]:
    """``path`` flock'ed through an open file of its own (as another process would)."""
    fd = os.open(path, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        yield fd
    finally:
        os.close(fd)


# -- the robot's claim, keyed on the endpoint ---------------------------------------------


@pytest.mark.parametrize("spelling", SPELLINGS)
def test_every_spelling_of_the_robots_address_meets_its_claim(locks: Path, spelling: str) -> None:
    with RobotClaim("modbus", "127.0.0.1:502", "the cellcal service on /data/a.db"):
        with (
            pytest.raises(CampaignError, match="is claimed by the cellcal service") as info,
            RobotClaim("modbus", spelling, "cellcal run on /data/b.db"),
        ):
            pytest.fail(f"{spelling} claimed the robot the service holds")
        assert f"modbus robot at {spelling}" in str(info.value)
        assert "127.0.0.1:502" in str(info.value)


def test_other_endpoints_are_other_robots(locks: Path) -> None:
    with RobotClaim("modbus", "localhost", "service"):
        for other in ("127.0.0.2:502", "127.0.0.1:503", "127.0.0.1:1502"):
            with RobotClaim("modbus", other, "run") as claim:
                assert claim.previous == ""


def test_a_ur_controller_is_its_host_whatever_the_spelling(locks: Path) -> None:
    with (
        RobotClaim("ur", "127.0.0.1", "service"),
        pytest.raises(CampaignError, match="ur robot at 0x7f000001"),
        RobotClaim("ur", "0x7f000001", "run"),
    ):
        pytest.fail("one UR controller claimed twice")


def test_a_host_that_does_not_resolve_is_one_line(locks: Path) -> None:
    with pytest.raises(CampaignError, match=r"robot\.address .*no-such-host\.invalid") as info:
        RobotClaim("modbus", "no-such-host.invalid:502", "run").__enter__()
    assert "\n" not in str(info.value)


def test_a_device_is_claimed_by_its_node_whatever_the_path(locks: Path, tmp_path: Path) -> None:
    link = tmp_path / "robot-port"
    link.symlink_to("/dev/null")
    with (
        RobotClaim("serial", "/dev/null", "service"),
        pytest.raises(CampaignError, match="is claimed by service"),
        RobotClaim("serial", str(link), "run"),
    ):
        pytest.fail("one device claimed through two paths")


def test_run_is_refused_on_another_spelling_before_anything_connects(
    locks: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(
        "\n".join(
            [
                'name = "claimed"',
                "[robot]",
                'driver = "modbus"',
                'address = "localhost:1593"',
                "[[sensor]]",
                'name = "tracker"',
                'kind = "laser-tracker"',
                'address = "socket://127.0.0.93:5593"',
                "reference = true",
                "[campaign]",
                "grid = [2, 2, 3]",
                "validation_inside = 4",
                "validation_per_region = 2",
                "validation_regions_mm = [[1000.0, 150.0, 550.0]]",
                "",
            ]
        )
    )
    db = tmp_path / "b.db"
    holder = "the cellcal service on /data/a.db (pid 1)"
    with RobotClaim("modbus", "127.0.0.1:1593", holder), pytest.raises(SystemExit) as info:
        main(["run", "--config", str(config), "--db", str(db)])
    assert info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "modbus robot at localhost:1593" in line and "is claimed by" in line, line
    assert not db.exists() or db.stat().st_size == 0


# -- planted lock files -------------------------------------------------------------------


def _claim_names(address: str) -> list[str]:
    """The claim's file names, before and after the fix (to plant at either)."""
    return [
        "cellcal-robot-modbus-" + address.replace(":", "_") + ".lock",
        "cellcal-robot-tcp-" + address.replace(":", "-") + ".lock",
    ]


def test_a_planted_symlink_is_not_followed(locks: Path, tmp_path: Path) -> None:
    victim = tmp_path / "shadow"
    victim.write_text("root:only\n")
    victim.chmod(0o600)
    for name in _claim_names("127.0.0.1:502"):
        (locks / name).symlink_to(victim)
    with pytest.raises(CampaignError, match="symbolic link") as info:
        RobotClaim("modbus", "127.0.0.1:502", "run").__enter__()
    assert "\n" not in str(info.value)
    assert victim.read_text() == "root:only\n"
    assert stat.S_IMODE(victim.stat().st_mode) == 0o600


def test_a_planted_symlink_beside_the_database_is_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    victim.chmod(0o600)
    db = tmp_path / "c.db"
    Path(f"{db}.lock").symlink_to(victim)
    with pytest.raises(CampaignError, match="symbolic link"):
        RunLock(str(db)).__enter__()
    assert victim.read_text() == "precious\n"
    assert stat.S_IMODE(victim.stat().st_mode) == 0o600


@pytest.mark.timeout(30)
def test_a_fifo_or_a_hard_link_as_a_lock_file_is_refused(locks: Path, tmp_path: Path) -> None:
    for name in _claim_names("127.0.0.1:502"):
        os.mkfifo(locks / name)
    with pytest.raises(CampaignError, match="not a regular file"):
        RobotClaim("modbus", "127.0.0.1:502", "run").__enter__()
    other = tmp_path / "other"
    other.write_text("x")
    for name in _claim_names("127.0.0.2:502"):
        os.link(other, locks / name)
    with pytest.raises(CampaignError, match="hard link"):
        RobotClaim("modbus", "127.0.0.2:502", "run").__enter__()
    assert other.read_text() == "x"


def test_an_existing_lock_file_keeps_its_mode(locks: Path) -> None:
    for name in _claim_names("127.0.0.1:502"):
        (locks / name).write_text("")
        (locks / name).chmod(0o600)
    with RobotClaim("modbus", "127.0.0.1:502", "run"):
        pass
    for name in _claim_names("127.0.0.1:502"):
        assert stat.S_IMODE((locks / name).stat().st_mode) == 0o600


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to make a file of another user")
def test_another_users_private_file_is_refused(locks: Path) -> None:
    for name in _claim_names("127.0.0.1:502"):
        path = locks / name
        path.write_text("theirs\n")
        path.chmod(0o600)
        os.chown(path, 65534, 65534)
    with pytest.raises(CampaignError, match="owned by uid 65534"):
        RobotClaim("modbus", "127.0.0.1:502", "run").__enter__()
    for name in _claim_names("127.0.0.1:502"):
        assert (locks / name).read_text() == "theirs\n"


# -- what the holder wrote -----------------------------------------------------------------


def test_the_holders_text_is_one_bounded_printable_line(locks: Path) -> None:
    evil = "\x1b[2J\x1b[31mcellcal: error: \u202eevil\x07\nsecond line\n" + "A" * 10000
    with RobotClaim("modbus", "127.0.0.1:502", "first"):
        pass
    (path,) = list(locks.iterdir())
    path.write_text(evil)
    for _ in _held_elsewhere(path):
        with pytest.raises(CampaignError) as info:
            RobotClaim("modbus", "127.0.0.1:502", "run").__enter__()
    message = str(info.value)
    assert "\n" not in message and "\x1b" not in message and "\x07" not in message
    assert "\u202e" not in message
    assert len(message) < 600, len(message)
    assert "second line" not in message
    assert "evil" in message and "holder wrote" in message, message
    with RobotClaim("modbus", "127.0.0.1:502", "next") as claim:
        assert "\x1b" not in claim.previous and "\n" not in claim.previous
        assert len(claim.previous) < 300


# -- the run lock, keyed on the database file ------------------------------------------


@pytest.fixture
def database(tmp_path: Path) -> Path:
    db = tmp_path / "a" / "c.db"
    db.parent.mkdir()
    db.write_bytes(b"")
    return db


def test_a_hard_link_to_the_database_meets_its_run_lock(
    locks: Path, database: Path, tmp_path: Path
) -> None:
    elsewhere = tmp_path / "b" / "same.db"
    elsewhere.parent.mkdir()
    os.link(database, elsewhere)
    beside = database.parent / "again.db"
    os.link(database, beside)
    with RunLock(str(database), "the cellcal service"):
        for other in (elsewhere, beside):
            with (
                pytest.raises(CampaignError, match="in use by the cellcal service"),
                RunLock(str(other)),
            ):
                pytest.fail(f"{other}: a second run on one database")


def test_a_symlink_to_the_database_meets_its_run_lock(
    locks: Path, database: Path, tmp_path: Path
) -> None:
    link = tmp_path / "link.db"
    link.symlink_to(database)
    with (
        RunLock(str(link), "cellcal run"),
        pytest.raises(CampaignError, match="in use by cellcal run"),
        RunLock(str(database)),
    ):
        pytest.fail("a second run on one database")


def test_without_a_lock_folder_a_hard_link_beside_still_meets_it(
    database: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("CELLCAL_LOCK_DIR", str(tmp_path / "no-such-folder"))
    beside = database.parent / "again.db"
    os.link(database, beside)
    with (
        RunLock(str(database), "first"),
        pytest.raises(CampaignError, match="in use by first"),
        RunLock(str(beside)),
    ):
        pytest.fail("a second run on one database")


def test_a_database_that_is_not_a_regular_file_is_refused(locks: Path, tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.db"
    os.mkfifo(fifo)
    with pytest.raises(CampaignError, match="not a regular file"):
        RunLock(str(fifo)).__enter__()
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_the_run_lock_leaves_no_empty_database_behind(locks: Path, tmp_path: Path) -> None:
    db = tmp_path / "new.db"
    with RunLock(str(db)) as lock:
        assert lock.previous == ""
    assert not db.exists()
    with RunLock(str(db)) as lock:  # it remembers who held it last
        assert lock.previous.startswith("cellcal run (pid ")
