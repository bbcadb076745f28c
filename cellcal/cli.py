"""The one entry point: ``cellcal <subcommand>``.

Each subcommand lives in its own module under ``cellcal.commands``. A user error
(:class:`cellcal.errors.UserError`, or a usage error) prints one line on stderr and
exits 2; a result refused by an acceptance check (:class:`cellcal.errors.AcceptanceError`)
prints one line naming the check and exits 3; success exits 0. Anything else is a bug
and keeps its traceback.

Ctrl-C (SIGINT) at any moment ends with one line, ``cellcal: interrupted``, and exit
130 — never a traceback. While cellcal loads (``python -m cellcal`` from the first line
of ``__main__``, the console script from the first lines here, before click) and once
the command has returned, there is nothing to unwind: the line, and the process ends at
once. While a command runs, the first Ctrl-C raises ``KeyboardInterrupt``, which unwinds
what the command holds (files, devices, twins) to :func:`main`; a second one meanwhile
ends at once. Commands that stop cleanly on it (``run``, ``daemon``) put their own
handler in place while they run. Called by a program of its own (the tests), ``main``
hands SIGINT back as it found it.
"""

from __future__ import annotations

# the interpreter's own, loaded at start-up: installing the handler waits for no import
import _signal  # type: ignore[import-not-found]
import os
import sys

if os.path.basename(sys.argv[0] if sys.argv else "") in ("cellcal", "cellcal.exe") and (
    getattr(sys.modules.get("__main__"), "__name__", "") == "__main__"
):
    # the console script: Ctrl-C from this line on is one line, before anything else
    # runs (_interrupted_now, below, takes over once it is defined)
    _signal.signal(
        _signal.SIGINT,
        lambda signum, frame: (os.write(2, b"cellcal: interrupted\n"), os._exit(130)),
    )

import contextlib

EXIT_INTERRUPTED = 130
INTERRUPTED = "cellcal: interrupted"
_said = False  # the line was written
_interrupted = False  # a KeyboardInterrupt is on its way
_resent = False  # it was dropped where Python ignores exceptions, and SIGINT sent again


def _say_interrupted() -> None:
    global _said
    if not _said:
        _said = True
        os.write(2, f"{INTERRUPTED}\n".encode())


def _interrupted_now(signum: int, frame: object) -> None:
    """Ctrl-C with nothing to unwind (cellcal loading, or ending): the line, exit 130."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a write this signal interrupted, a pipe gone
            stream.flush()
    _say_interrupted()
    os._exit(EXIT_INTERRUPTED)


def _is_the_program() -> bool:
    """Whether this process is the ``cellcal`` console script (not a program that
    imports this module: the tests)."""
    main_module = sys.modules.get("__main__")
    name = os.path.basename(sys.argv[0]) if sys.argv else ""
    return name in ("cellcal", "cellcal.exe") and getattr(main_module, "__name__", "") == "__main__"


if _is_the_program():
    _signal.signal(_signal.SIGINT, _interrupted_now)

import _thread  # noqa: E402 - after the handler: Ctrl-C while they load is one line
import atexit  # noqa: E402
import importlib  # noqa: E402
import signal  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

import click  # noqa: E402

from cellcal import __version__  # noqa: E402
from cellcal.errors import AcceptanceError, UserError  # noqa: E402
from cellcal.extras import needs  # noqa: E402

_sending = threading.Lock()  # SIGINT sent again (_send_again) or not
EXIT_USER_ERROR = 2
EXIT_REFUSED = 3


#: Every subcommand: where it lives, and its one-line help (the first sentence of its
#: docstring, shown by ``cellcal --help`` without importing it; a test keeps the two
#: equal). A subcommand's module is imported only when it runs, so that ``--version``
#: and ``--help`` do not load numpy, OpenCV, Pinocchio or matplotlib.
COMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": (
        "cellcal.commands.calibrate:calibrate",
        "Identify the kinematic errors from measured target positions.",
    ),
    "campaign": (
        "cellcal.commands.campaign:campaign",
        "Start, control and watch campaigns in the cell service; list a database's.",
    ),
    "check": (
        "cellcal.commands.check:check",
        "Check the robot against its current model between calibrations: a few poses "
        "measured like a calibration's, their errors against limits from the model's own "
        "uncertainty and earlier checks, a verdict (ok, warning, recalibrate) and its likely "
        "cause.",
    ),
    "compensate": (
        "cellcal.commands.compensate:compensate_command",
        "Joint targets that bring the real robot's target to intended points.",
    ),
    "daemon": (
        "cellcal.commands.daemon:daemon",
        "The cell service: holds the devices, runs queued campaigns, answers the "
        "``cellcal campaign`` commands on its control socket.",
    ),
    "export": (
        "cellcal.commands.export:export",
        "Write a robot model in another program's format, or the program a controller runs.",
    ),
    "fleet": (
        "cellcal.commands.fleet:fleet",
        "A cell's replication to the fleet's PostgreSQL, and the fleet's page.",
    ),
    "iso9283": (
        "cellcal.commands.iso9283:iso9283",
        "ISO 9283 pose accuracy (AP) and repeatability (RP) at the standard's five points of "
        "the campaign's cube: with the nominal model's joints, then the calibrated model's.",
    ),
    "mock": (
        "cellcal.commands.mock:mock",
        "Serve the simulated cell's devices over their real wire protocols.",
    ),
    "models": (
        "cellcal.commands.models:models",
        "List the built-in robot models (use the name with --model); with --cell, the models "
        "the cell has carried: since when, until when and why, and the checks since.",
    ),
    "plan": (
        "cellcal.commands.plan:plan",
        "Every pose of the campaign's plan, reachable or not and why, the condition number "
        "of the calibration poses and the parameters they identify, and the cell time it "
        "takes, and the error a calibration from these poses is expected to leave in the "
        "cube and the validation regions (in units of the sensor's noise); nothing connects "
        "or moves.",
    ),
    "predict": (
        "cellcal.commands.predict:predict",
        "Positions of the target (mm) for joint readings.",
    ),
    "register": (
        "cellcal.commands.register:register",
        "Fit T_dst_src from common points matched by name.",
    ),
    "report": (
        "cellcal.commands.report:report",
        "Write a campaign's report folder: index.html (the report: self-contained, figures "
        "inline), summary.json, model.toml, poses.csv, measurements-<sensor>.csv (the "
        "calibrate format), validation-<sensor>.csv.",
    ),
    "rig": (
        "cellcal.commands.rig:rig",
        "The photogrammetry rig: calibrate it from ChArUco views, measure the target.",
    ),
    "run": (
        "cellcal.commands.run:run",
        "Run a whole campaign: plan, acquire, store, register, calibrate, validate, report.",
    ),
    "service": ("cellcal.commands.service:service", "The systemd service of this installation."),
    "tracker": (
        "cellcal.commands.tracker:tracker",
        "Connect to a tracker, identify it, initialise it and measure its target; or check "
        "its line protocol (--conformance).",
    ),
}
#: Subcommands that live in another module than their group's: group → (name, where).
#: (``cellcal mock``'s come from the registry of device families: ``commands/mock.py``.)
EXTRA = {
    "rig": ("capture", "cellcal.commands.rig_capture:rig_capture"),
}


def _load(where: str, name: str) -> click.Command:
    """The command at ``where``; a command module that needs an optional library that
    is not installed (the service's aiohttp, the report's matplotlib, the rig's OpenCV)
    ends in one line naming the extra (``cellcal.extras``)."""
    module, _, attribute = where.partition(":")
    with needs(f"cellcal {name}"):
        command = getattr(importlib.import_module(module), attribute)
    assert isinstance(command, click.Command)
    return command


class LazyGroup(click.Group):
    """A group whose subcommands are imported when they run (:data:`COMMANDS`)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        command = _load(COMMANDS[cmd_name][0], cmd_name)
        if cmd_name in EXTRA and isinstance(command, click.Group):
            name, where = EXTRA[cmd_name]
            if name not in command.commands:
                command.add_command(_load(where, f"{cmd_name} {name}"), name)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        limit = formatter.width - 6 - max(len(name) for name in COMMANDS)
        rows = [
            (name, click.Command(name, help=COMMANDS[name][1]).get_short_help_str(limit))
            for name in self.list_commands(ctx)
        ]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
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
    import logging

    level = {0: logging.ERROR, 1: logging.WARNING}.get(verbose, logging.INFO)
    logging.basicConfig(level=level, format="cellcal: %(name)s: %(message)s", force=True)


def _interrupt_once(signum: int, frame: object) -> None:
    """Ctrl-C while a command runs: ``KeyboardInterrupt`` (unwound to :func:`main`); a
    second one before that is done ends at once."""
    global _interrupted, _resent
    if _said:  # sent again (below), but main has said the line meanwhile
        return
    if _interrupted and not _resent:
        _interrupted_now(signum, frame)
    _interrupted, _resent = True, False
    raise KeyboardInterrupt


def _unraisable_interrupt(hook: Callable[[Any], object]) -> Callable[[Any], object]:
    """``sys.unraisablehook`` that keeps quiet about the KeyboardInterrupt of
    :func:`_interrupt_once` and passes anything else to ``hook``. Python drops an
    exception raised where it cannot propagate (a weakref callback of importlib's while
    a command's modules load): that Ctrl-C is sent again, so that it reaches the command
    at its next line instead of when it has done all its work (a whole campaign)."""

    def unraisable(args: Any) -> object:
        try:
            if isinstance(args.exc_value, KeyboardInterrupt) and _interrupted:
                if not _said:
                    _send_again()
                return None
            return hook(args)
        except KeyboardInterrupt:  # the one sent again came before this returned
            _send_again()
            return None

    return unraisable


def _send_again() -> None:
    """SIGINT to the main thread again, from a thread of its own a millisecond later
    (raised here, in the hook, it would be dropped again), unless :func:`main` has
    ended meanwhile (:func:`_no_more_sent`)."""
    global _resent
    with _sending:
        _resent = True

    def later() -> None:
        time.sleep(0.001)
        with _sending:
            if _resent:
                _thread.interrupt_main()

    _thread.start_new_thread(later, ())


def _no_more_sent() -> None:
    """No SIGINT is sent again from now on; one sent already is handled here, while
    :func:`_interrupt_once` is still the handler (it returns: the line is said)."""
    global _resent
    with _sending:
        _resent = False
    _signals_run()


def _signals_run() -> None:
    """Nothing: calling it is where Python runs the handlers of signals received."""


def _stop_interrupted(here: bool) -> int:
    """The line for an interrupt that reached :func:`main`; its exit code."""
    global _said
    if here:  # nothing more to interrupt: the line, and the end
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    _said = True
    click.echo(INTERRUPTED, err=True)
    return EXIT_INTERRUPTED


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point; turns user errors into one line and exit code 2, and
    Ctrl-C into one line and exit code 130."""
    global _said, _interrupted, _resent
    _said = _interrupted = _resent = False
    program = argv is None
    here = threading.current_thread() is threading.main_thread()
    # Until the handler below is in place a Ctrl-C meets the one before it (the
    # program's: the line and exit 130). From the moment it is, it may fire at any
    # bytecode, so it is installed inside the try that turns it into the line.
    previous: Any = signal.getsignal(signal.SIGINT)
    hook = sys.unraisablehook
    try:
        if here:
            sys.unraisablehook = _unraisable_interrupt(hook)
            previous = signal.signal(signal.SIGINT, _interrupt_once)
        code = _run(sys.argv[1:] if argv is None else list(argv), program)
        if _interrupted and not _said:
            # the KeyboardInterrupt was raised where Python drops exceptions (a weakref
            # callback of importlib's): the command went on, but Ctrl-C was heard
            code = _stop_interrupted(here)
    except Exception:
        if not _interrupted:
            raise
        # Ctrl-C while an extension module initialises surfaces as that import's error
        # ("ImportError: initialization failed", scipy's HiGHS): still the interrupt.
        code = _stop_interrupted(here)
    except KeyboardInterrupt:
        code = _stop_interrupted(here)
    finally:
        sys.unraisablehook = hook
        if here:
            _no_more_sent()
            # The program ends now: a Ctrl-C while it does is the line and exit 130.
            signal.signal(signal.SIGINT, _interrupted_now if program else previous)
    if program and _said:
        # The interpreter ends a process whose KeyboardInterrupt went through code run
        # for an extension (pybind11's eval) with SIGINT itself (exit -2), caught or not:
        # the at-exit work, then exit 130.
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(EXIT_INTERRUPTED)
    sys.exit(code)


def _run(args: list[str], program: bool) -> int:
    """The command's exit code; its errors as one line."""
    try:
        with cli.make_context("cellcal", args) as ctx:
            rv = cli.invoke(ctx)
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except UserError as exc:
        click.echo(f"cellcal: error: {exc}", err=True)
        return EXIT_USER_ERROR
    except AcceptanceError as exc:
        click.echo(f"cellcal: refused: {exc}", err=True)
        return EXIT_REFUSED
    except click.exceptions.NoArgsIsHelpError as exc:
        click.echo(exc.ctx.get_help() if exc.ctx else "", err=False)
        return 0
    except click.ClickException as exc:
        msg = " ".join(exc.format_message().split())
        click.echo(f"cellcal: error: {msg}", err=True)
        return EXIT_USER_ERROR
    except (click.exceptions.Abort, EOFError):
        raise KeyboardInterrupt from None
    except BrokenPipeError:
        if program:  # the reader has gone: nothing more to say, not even at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    return rv if isinstance(rv, int) else 0
