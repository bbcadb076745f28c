"""``cellcal mock …``: the simulated cell's devices as protocol-level servers.

The subcommands are the twins of the registry of device families
(``cellcal/families.py``, cellcal's table and the families of installed distributions):
one per family with a twin, named by its line (``mock``, else its driver). A line that
names its own click command (``mock_command``: ``tracker``, ``modbus-robot``, ``ur``
here, ``cameras`` in ``rig_capture.py``) gets it; any other gets
:func:`family_command`, which serves the configured device's twin as mock mode does.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType
from typing import TYPE_CHECKING, Any, Protocol

import click

from cellcal.commands.output import NON_NEGATIVE, SEED, TIME_SCALE
from cellcal.config import CellConfig, load_config
from cellcal.errors import InputError
from cellcal.families import Family, FamilyError, load, registered
from cellcal.files.models import load_model

if TYPE_CHECKING:
    from cellcal.families import SimulatedCell


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(f"--listen {text!r}: expected HOST:PORT, e.g. 127.0.0.5:5555")
    return host, int(port)


def wait_for_signal() -> None:
    done = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        done.set()

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, on_signal)
    while not done.wait(0.5):
        pass


def twins() -> dict[str, Family]:
    """``cellcal mock`` subcommand → its family: every registered family with a twin."""
    return {f.mock_name: f for f in registered() if f.mock_name is not None}


def command_of(family: Family, name: str) -> click.Command:
    """The family's ``cellcal mock`` command: the one its line names, else made here."""
    if family.mock_command is None:
        return family_command(family, name)
    command = load(family.mock_command)
    if not isinstance(command, click.Command):
        where = family.origin or "cellcal"
        raise FamilyError(f"{where}: {family.mock_command} is not a click command")
    return command


class MockGroup(click.Group):
    """``cellcal mock``: a subcommand per twin of the registry (:func:`twins`)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(twins())

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        family = twins().get(cmd_name)
        return None if family is None else command_of(family, cmd_name)


@click.group(cls=MockGroup)
def mock() -> None:
    """Serve the simulated cell's devices over their real wire protocols."""


@click.command("tracker")
@click.option(
    "--dialect",
    type=click.Choice(["line-protocol", "emscon"]),
    default="line-protocol",
    show_default=True,
    help="cellcal's line protocol, or Leica's emScon TPI (binary, TCP only; its faults "
    "from the configuration's [simulation.faults]).",
)
@click.option("--listen", help="TCP address HOST:PORT (a 127.0.0.x address for tests).")
@click.option("--pty", "use_pty", is_flag=True, help="Serve on a pseudo-terminal instead.")
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled simulated cell)."
)
@click.option("--sensor", default=None, help="Which laser-tracker sensor of the configuration.")
@click.option("--seed", type=SEED, help="Seed of the simulated truth and noise.")
@click.option(
    "--beam-break-after", type=int, help="Fault: break the beam after N points of a series."
)
@click.option(
    "--beam-breaks",
    type=int,
    default=1,
    show_default=True,
    help="Fault: consecutive broken series.",
)
@click.option(
    "--garbage-every", type=int, default=0, help="Fault: a garbage line before every k-th line."
)
@click.option(
    "--event-every",
    type=int,
    default=0,
    help="Fault: an unsolicited event before every k-th reply.",
)
@click.option(
    "--reply-delay", type=NON_NEGATIVE, default=0.0, help="Fault: seconds before every reply."
)
@click.option("--drop-after", type=int, help="Fault: drop the connection after N lines.")
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=1.0,
    show_default=True,
    help="Wall seconds per tracker second (pacing of points).",
)
def mock_tracker(
    dialect: str,
    listen: str | None,
    use_pty: bool,
    config_path: str | None,
    sensor: str | None,
    seed: int | None,
    beam_break_after: int | None,
    beam_breaks: int,
    garbage_every: int,
    event_every: int,
    reply_delay: float,
    drop_after: int | None,
    time_scale: float,
) -> None:
    """A laser tracker of the simulated cell, speaking the tracker line protocol (or
    Leica's emScon TPI)."""
    from cellcal.commands.run import bundled_mock_cell
    from cellcal.families import SimulatedCell, TrackerFaults, TrackerTwin, emscon_twin

    if (listen is None) == (not use_pty):
        raise InputError("give --listen HOST:PORT or --pty")
    line_only = {
        "--pty": use_pty,
        "--beam-break-after": beam_break_after is not None,
        "--garbage-every": garbage_every != 0,
        "--event-every": event_every != 0,
        "--reply-delay": reply_delay != 0.0,
        "--drop-after": drop_after is not None,
    }
    if dialect == "emscon" and any(line_only.values()):
        given = ", ".join(k for k, v in line_only.items() if v)
        raise InputError(
            f"{given}: for the line protocol; the emScon twin takes its faults from the "
            "configuration's [simulation.faults]"
        )
    config = load_config(config_path) if config_path else bundled_mock_cell()[0]
    trackers = [s.name for s in config.sensor if s.kind == "laser-tracker"]
    name = sensor or (trackers[0] if trackers else None)
    if name is None or name not in trackers:
        raise InputError(
            f"no laser-tracker sensor {sensor!r} in the configuration ({', '.join(trackers)})"
        )
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed)
    if dialect == "emscon":
        assert listen is not None
        twin = emscon_twin(cell, name, time_scale)
        try:
            host, port = twin.start_tcp(*_host_port(listen))
        except OSError as exc:
            raise InputError(f"--listen {listen}: cannot listen ({exc.strerror})") from None
        with twin:
            click.echo(
                f"emScon tracker {name!r} of {config.name!r} serving on {host}:{port}", err=True
            )
            click.echo(f"{host}:{port}")
            wait_for_signal()
        return
    faults = TrackerFaults(
        beam_break_after=beam_break_after,
        beam_breaks=beam_breaks,
        garbage_every=garbage_every,
        event_every=event_every,
        reply_delay_s=reply_delay,
        drop_after_lines=drop_after,
    )
    server = TrackerTwin(cell.target(name), faults=faults, time_scale=time_scale)
    with server:
        if use_pty:
            where = server.start_pty()
        else:
            assert listen is not None
            try:
                host, port = server.start_tcp(*_host_port(listen))
            except OSError as exc:
                raise InputError(f"--listen {listen}: cannot listen ({exc.strerror})") from None
            where = f"socket://{host}:{port}"
        click.echo(f"tracker twin {name!r} of {config.name!r} serving on {where}", err=True)
        click.echo(where)
        wait_for_signal()


def simulated_cell_of(
    config_path: str | None, seed: int | None
) -> tuple[CellConfig, SimulatedCell]:
    from cellcal.commands.run import bundled_mock_cell
    from cellcal.families import SimulatedCell

    config = load_config(config_path) if config_path else bundled_mock_cell()[0]
    return config, SimulatedCell(config, load_model(config.robot.model).model, seed)


@click.command("modbus-robot")
@click.option(
    "--listen", required=True, help="TCP address HOST:PORT (a 127.0.0.x address for tests)."
)
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled simulated cell)."
)
@click.option("--seed", type=SEED, help="Seed of the simulated truth.")
@click.option(
    "--word-order",
    type=click.Choice(["big", "little"]),
    help="Float32 word order (default: the configuration's).",
)
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=1.0,
    show_default=True,
    help="Wall seconds per second of motion.",
)
@click.option("--no-ack", is_flag=True, help="Fault: never acknowledge commands.")
@click.option("--error-code", type=int, help="Fault: set the error bit with this code on a move.")
@click.option("--estop", is_flag=True, help="Fault: e-stop on a move.")
@click.option("--stale-heartbeat", is_flag=True, help="Fault: the heartbeat stops.")
def mock_modbus_robot(
    listen: str,
    config_path: str | None,
    seed: int | None,
    word_order: str | None,
    time_scale: float,
    no_ack: bool,
    error_code: int | None,
    estop: bool,
    stale_heartbeat: bool,
) -> None:
    """The configured Modbus robot's twin: its map, word order and device id (docs/robots.md)."""
    import math

    from cellcal.drivers.modbus_options import ModbusRobotOptions
    from cellcal.families import ModbusRobotFaults, ModbusRobotTwin, limits_deg, xyzabc

    config, cell = simulated_cell_of(config_path, seed)
    robot = config.robot
    if not isinstance(robot, ModbusRobotOptions):
        raise InputError(
            f"the configuration's robot has driver = {robot.driver!r}, not a Modbus robot"
        )
    modbus_map = robot.map
    if word_order is not None:
        modbus_map = modbus_map.model_copy(update={"word_order": word_order})
    sim = ModbusRobotTwin(
        q0_deg=list(robot.home_deg),
        limits_deg=limits_deg(cell),
        joint_speed_deg_s=math.degrees(cell.joint_speed),
        time_scale=time_scale,
        map=modbus_map,
        faults=ModbusRobotFaults(
            no_ack=no_ack, error_code=error_code, estop=estop, stale_heartbeat=stale_heartbeat
        ),
        on_move=cell.set_q,
        pose_fn=lambda q: xyzabc(cell.flange_pose(q)),
    )
    serve_until_signal(sim, listen, "mock Modbus robot serving on {}")


class _Startable(Protocol):
    def start(self, host: str, port: int = 0) -> tuple[str, int]: ...
    def stop(self) -> None: ...


def serve_until_signal(twin: _Startable, listen: str, banner: str, scheme: str = "") -> None:
    """Start ``twin`` on ``--listen`` HOST:PORT, say where on stderr (``banner`` with
    ``{}`` for the address) and print it on stdout (with ``scheme``: ``http://``), serve
    until Ctrl-C or SIGTERM, then stop it."""
    try:
        host, port = twin.start(*_host_port(listen))
    except (OSError, RuntimeError) as exc:
        raise InputError(f"--listen {listen}: cannot listen ({exc})") from None
    try:
        where = f"{scheme}{host}:{port}"
        click.echo(banner.format(where), err=True)
        click.echo(where)
        wait_for_signal()
    finally:
        twin.stop()


@click.command("ur")
@click.option(
    "--host",
    required=True,
    help="Loopback address to bind (RTDE 30004, dashboard 29999, script 30003).",
)
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled UR10e cell)."
)
@click.option("--seed", type=SEED, help="Seed of the simulated truth.")
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=1.0,
    show_default=True,
    help="Wall seconds per second of motion.",
)
def mock_ur(host: str, config_path: str | None, seed: int | None, time_scale: float) -> None:
    """A Universal Robots controller that the unmodified ur_rtde library can drive."""
    from importlib import resources

    from cellcal.families import twin_for_cell

    ref = resources.files("cellcal") / "data" / "mock-cell-ur10e.toml"
    with resources.as_file(ref) as bundled:
        config, cell = simulated_cell_of(config_path or str(bundled), seed)
    sim = twin_for_cell(cell, config.robot.home_deg, time_scale)
    try:
        sim.start(host)
    except OSError as exc:
        raise InputError(f"--host {host}: cannot bind the UR ports ({exc})") from None
    try:
        click.echo(f"mock UR controller serving on {host} (30004, 29999, 30003)", err=True)
        click.echo(host)
        wait_for_signal()
    finally:
        sim.stop()


def family_command(family: Family, name: str) -> click.Command:
    """``cellcal mock <name>`` for a family whose line names no command of its own: the
    twin of the configured device of that family, as mock mode starts it, until Ctrl-C
    or SIGTERM; where it serves on stdout."""
    params: list[click.Parameter] = [
        click.Option(
            ["--config", "config_path"],
            required=True,
            help=f"Cell configuration with a {family.tag} device.",
        ),
        click.Option(["--seed"], type=SEED, help="Seed of the simulated truth and noise."),
        click.Option(
            ["--time-scale"],
            type=TIME_SCALE,
            default=1.0,
            show_default=True,
            help="Wall seconds per second of the device.",
        ),
    ]
    if family.role == "sensor":
        params.insert(
            1,
            click.Option(
                ["--sensor"], default=None, help=f"Which {family.tag} sensor (default: the first)."
            ),
        )

    def run(**options: Any) -> None:
        serve_family(family, **options)

    return click.Command(
        name,
        callback=run,
        params=params,
        help=f"The twin of a {family.tag} device ({family.summary}), served until Ctrl-C "
        "or SIGTERM; prints where it serves.",
    )


def serve_family(
    family: Family,
    config_path: str,
    seed: int | None,
    time_scale: float,
    sensor: str | None = None,
) -> None:
    """Serve the twin of the configuration's device of ``family`` (the robot, or the
    sensor named, else the first of the family) until Ctrl-C or SIGTERM."""
    assert family.twin is not None
    config, cell = simulated_cell_of(config_path, seed)
    if family.role == "robot":
        if config.robot.driver != family.driver:
            raise InputError(
                f"{config_path}: the robot has driver = {config.robot.driver!r}, "
                f"not {family.driver!r}"
            )
        options: Any = config.robot
        name = "robot"
    else:
        mine = [s for s in config.sensor if (s.kind, s.driver) == (family.kind, family.driver)]
        names = ", ".join(s.name for s in mine) or "none"
        options = next((s for s in mine if sensor is None or s.name == sensor), None)
        if options is None:
            what = f"sensor {sensor!r}" if sensor is not None else "sensor"
            raise InputError(f"no {family.tag} {what} in {config_path} (its: {names})")
        name = options.name
    # the twin alone: the driver's libraries are not its
    twin = load(family.twin, libraries=False)(options, cell, time_scale)
    try:
        where = twin.options.address if family.role == "robot" else twin.options.endpoint()
        click.echo(f"mock {family.tag} {name!r} of {config.name!r} serving on {where}", err=True)
        click.echo(where)
        wait_for_signal()
    finally:
        twin.stop()
