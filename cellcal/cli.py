"""The one entry point: ``cellcal <subcommand>``.

Each subcommand lives in its own module under ``cellcal.commands``. A user error
(:class:`cellcal.errors.UserError`, or a usage error) prints one line on stderr and
exits 2; a result refused by an acceptance check (:class:`cellcal.errors.AcceptanceError`)
prints one line naming the check and exits 3; success exits 0. Anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

import logging
import sys

import click

from cellcal import __version__
from cellcal.commands.calibrate import calibrate
from cellcal.commands.campaign import campaign
from cellcal.commands.compensate import compensate_command
from cellcal.commands.daemon import daemon
from cellcal.commands.export import export
from cellcal.commands.iso9283 import iso9283
from cellcal.commands.mock import mock
from cellcal.commands.models import models
from cellcal.commands.plan import plan
from cellcal.commands.predict import predict
from cellcal.commands.register import register
from cellcal.commands.report import report
from cellcal.commands.rig import rig
from cellcal.commands.rig_capture import mock_cameras, rig_capture
from cellcal.commands.run import run
from cellcal.commands.service import service
from cellcal.commands.tracker import tracker
from cellcal.errors import AcceptanceError, UserError

EXIT_USER_ERROR = 2
EXIT_REFUSED = 3


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="cellcal")
@click.option(
    "-v", "--verbose", count=True, help="Log device retries (-v) and events (-vv) on stderr."
)
def cli(verbose: int) -> None:
    """cellcal: online calibration of industrial robot cells.

    Registers sensor frames to the robot base from common points, and (as the project
    grows) identifies the robot's kinematic errors from laser-tracker and photogrammetry
    campaigns. Lengths are millimetres and angles degrees at every boundary.
    """
    level = {0: logging.ERROR, 1: logging.WARNING}.get(verbose, logging.INFO)
    logging.basicConfig(level=level, format="cellcal: %(name)s: %(message)s", force=True)


for command in (
    run,
    register,
    calibrate,
    predict,
    models,
    tracker,
    mock,
    report,
    campaign,
    rig,
    daemon,
    service,
    compensate_command,
    iso9283,
    export,
    plan,
):
    cli.add_command(command)
rig.add_command(rig_capture)
mock.add_command(mock_cameras)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point; turns user errors into one line and exit code 2."""
    try:
        rv = cli.main(args=argv, prog_name="cellcal", standalone_mode=False)
    except UserError as exc:
        click.echo(f"cellcal: error: {exc}", err=True)
        sys.exit(EXIT_USER_ERROR)
    except AcceptanceError as exc:
        click.echo(f"cellcal: refused: {exc}", err=True)
        sys.exit(EXIT_REFUSED)
    except click.exceptions.NoArgsIsHelpError as exc:
        click.echo(exc.ctx.get_help() if exc.ctx else "", err=False)
        sys.exit(0)
    except click.ClickException as exc:
        msg = " ".join(exc.format_message().split())
        click.echo(f"cellcal: error: {msg}", err=True)
        sys.exit(EXIT_USER_ERROR)
    except click.exceptions.Abort:
        click.echo("cellcal: interrupted", err=True)
        sys.exit(130)
    except BrokenPipeError:
        sys.exit(0)
    sys.exit(rv if isinstance(rv, int) else 0)
