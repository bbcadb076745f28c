"""``cellcal service install``: the systemd unit for this installation, checked, written
(or only shown with ``--dry-run``), and the commands that enable and start it. It
creates nothing silently: no user, no group, no folder; what is missing is named with
the command that makes it."""

from __future__ import annotations

import contextlib
import grp
import pwd
import stat
import sys
from pathlib import Path

import click

from cellcal.config import load_config
from cellcal.config_files import check_named_files
from cellcal.errors import CampaignError, InputError
from cellcal.extras import require
from cellcal.files.outputs import check_output_file
from cellcal.files.text import read_text
from cellcal.service.unitfile import (
    CHECK_SERVICE,
    CHECK_TIMER,
    UNIT_NAME,
    render,
    render_check,
    verify,
)

DEFAULT_CONFIG = "/etc/cellcal/cell.toml"
UNIT_DIR = "/etc/systemd/system"
#: Where systemctl looks for units by name.
SEARCH_PATH = (
    "/etc/systemd/system",
    "/run/systemd/system",
    "/lib/systemd/system",
    "/usr/lib/systemd/system",
)


@click.group()
def service() -> None:
    """The systemd service of this installation."""


@service.command()
@click.option(
    "--config",
    "config_path",
    default=DEFAULT_CONFIG,
    show_default=True,
    help="The cell configuration the service runs.",
)
@click.option("--venv", help="The virtual environment of cellcal (default: this one).")
@click.option("--user", default="cellcal", show_default=True, help="The service's user.")
@click.option("--dry-run", is_flag=True, help="Print the unit and check it; write nothing.")
@click.option("--unit-dir", default=UNIT_DIR, show_default=True, help="Where the unit goes.")
@click.option("--force", is_flag=True, help="Replace a cellcal.service that differs.")
@click.option(
    "--check-every",
    "every",
    help="Also a timer that queues a check between calibrations this often (a systemd "
    "time span: 7d, 12h, 1w).",
)
def install(
    config_path: str,
    venv: str | None,
    user: str,
    dry_run: bool,
    unit_dir: str,
    force: bool,
    every: str | None,
) -> int:
    """Render the unit for this installation, check it with systemd-analyze verify,
    write it, and say the two commands that enable and start the service; with
    --check-every, also cellcal-check.timer and its service, which queue a check."""
    # what the unit runs: cellcal daemon, which writes each campaign's report
    require("the cell service", "aiohttp", "matplotlib")
    config = Path(config_path).resolve()
    if not config.is_file():
        raise InputError(f"--config {config}: no such file (write the cell's configuration first)")
    # a configuration the service would refuse is refused now, and so are the files it
    # names (a rig's calibration…): the service would retry a missing one for ever
    check_named_files(load_config(str(config)), str(config))
    prefix = Path(venv).resolve() if venv else Path(sys.prefix)
    if not (prefix / "bin" / "cellcal").is_file():
        raise InputError(f"--venv {prefix}: no bin/cellcal there (give cellcal's venv)")
    _reachable(prefix, user)
    text = render(prefix, config, user)
    timer = {} if every is None else render_check(prefix, config, user, every)
    checked = verify(text, others=timer)
    if not checked.ok:
        raise CampaignError(f"the rendered unit does not pass: {checked.message}")
    if dry_run:
        click.echo(text, nl=False)
        for name, other in timer.items():
            click.echo(f"# --- {name}")
            click.echo(other, nl=False)
        click.echo(f"# {checked.message}; --dry-run: nothing written", err=True)
        return 0
    _user_exists(user)
    files = {UNIT_NAME: text, **timer}
    targets = {Path(unit_dir) / name: body for name, body in files.items()}
    said = {target: _differs(target, body, force) for target, body in targets.items()}
    for target, body in targets.items():
        if said[target] == "written":
            _write(target, body, unit_dir)
        click.echo(f"{target}: {said[target]} ({checked.message})")
    if pwd.getpwnam(user).pw_uid == 0:
        click.echo(f"the service runs as {user}: operators reach its socket with sudo")
    else:
        click.echo(f"operators join group {user}: sudo usermod -aG {user} NAME (then log in again)")
    # systemctl finds a unit outside its search path only when given the file's path
    where = Path(unit_dir).resolve()
    unit = UNIT_NAME if str(where) in SEARCH_PATH else str(where / UNIT_NAME)
    click.echo("to enable and start the service:")
    click.echo(f"  sudo systemctl daemon-reload && sudo systemctl enable {unit}")
    click.echo(f"  sudo systemctl start {UNIT_NAME}")
    if timer:
        timer_unit = CHECK_TIMER if str(where) in SEARCH_PATH else str(where / CHECK_TIMER)
        if timer_unit != CHECK_TIMER:
            click.echo(f"  sudo systemctl link {where / CHECK_SERVICE}")
        click.echo(f"and the checks every {' '.join(every.split())}:")  # type: ignore[union-attr]
        click.echo(f"  sudo systemctl enable --now {timer_unit}")
    return 0


def _differs(target: Path, text: str, force: bool) -> str:
    """``unchanged`` or ``written`` (to be): a file there that differs is refused
    without ``--force``, before anything is written."""
    check_output_file(target)  # a FIFO would hang the reading, a device take the writing
    current = read_text(target, "a unit file") if target.exists() else None
    if current is not None and current != text and not force:
        raise CampaignError(f"{target} exists and differs (see --dry-run); --force replaces it")
    return "unchanged" if current == text else "written"


def _write(target: Path, text: str, unit_dir: str) -> None:
    try:
        target.write_text(text)
    except PermissionError:
        raise InputError(f"{target}: permission denied (run it with sudo)") from None
    except FileNotFoundError:
        raise InputError(f"{unit_dir}: no such folder (is systemd installed?)") from None


def _reachable(prefix: Path, user: str) -> None:
    """The service's user must be able to run the venv's cellcal and its interpreter:
    every folder on their paths searchable and the files executable for that user (by
    the owner, group or other bits; root needs one x bit on a file). A user that does
    not exist yet is not checked here (``_user_exists`` names the command)."""
    try:
        who = pwd.getpwnam(user)
    except KeyError:
        return
    groups = {who.pw_gid} | {g.gr_gid for g in grp.getgrall() if user in g.gr_mem}
    exe = prefix / "bin" / "cellcal"
    paths = [exe]
    with contextlib.suppress(OSError, UnicodeDecodeError):
        first = exe.read_bytes()[:512].split(b"\n", 1)[0].decode()
        if first.startswith("#!") and first[2:].strip():
            paths.append(Path(first[2:].split()[0]))
    for path in [*paths, *(p.resolve() for p in paths)]:
        blocked = _blocked(path, who.pw_uid, groups)
        if blocked is not None:
            raise InputError(
                f"--venv {prefix}: user {user} cannot execute {path} ({blocked} is not "
                f"{'executable' if blocked == path else 'searchable'} for {user}); "
                "put the venv where the service's user can reach it (e.g. /opt/cellcal)"
            )


def _blocked(path: Path, uid: int, groups: set[int]) -> Path | None:
    """The first folder on ``path`` (or the file itself) that ``uid`` cannot search or
    execute, going down from /."""
    for p in [*reversed(path.parents), path]:
        try:
            st = p.stat()
        except OSError:
            return p
        if uid == 0:
            if p == path and not st.st_mode & 0o111:
                return p
            continue
        if st.st_uid == uid:
            bit = stat.S_IXUSR
        elif st.st_gid in groups:
            bit = stat.S_IXGRP
        else:
            bit = stat.S_IXOTH
        if not st.st_mode & bit:
            return p
    return None


def _user_exists(user: str) -> None:
    """The service's user and its group: named with the command that makes them."""
    make = (
        f"sudo useradd --system --user-group --home-dir /var/lib/cellcal "
        f"--shell /usr/sbin/nologin {user}"
    )
    try:
        pwd.getpwnam(user)
        grp.getgrnam(user)
    except KeyError:
        raise InputError(f"no user and group {user!r} on this PC; make them: {make}") from None
