"""``cellcal mock kuka-kvp``, ``kuka-eki``, ``abb-rws`` and ``fanuc-rmi``: the twins of
the robot controllers reached through their own interfaces (docs/robots.md), each
serving the simulated cell's robot as the controller running cellcal's program (or
FANUC's RMI) would."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from cellcal.commands.mock import serve_until_signal, simulated_cell_of
from cellcal.commands.output import SEED, TIME_SCALE


def _cell_options(where: Any) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """The options every controller twin here takes: ``where`` (its address option),
    which cell, which truth, how fast."""

    def add(f: Callable[..., None]) -> Callable[..., None]:
        for option in reversed(
            [
                where,
                click.option(
                    "--config",
                    "config_path",
                    help="Cell configuration (default: the bundled cell); its robot's home "
                    "and model are served.",
                ),
                click.option("--seed", type=SEED, help="Seed of the simulated truth."),
                click.option(
                    "--time-scale",
                    type=TIME_SCALE,
                    default=1.0,
                    show_default=True,
                    help="Wall seconds per second of motion (and of a controller's timeouts).",
                ),
            ]
        ):
            f = option(f)
        return f

    return add


_twin_options = _cell_options(
    click.option(
        "--listen", required=True, help="Address HOST:PORT (a 127.0.0.x address for tests)."
    )
)


def _kuka_options(f: Callable[..., None]) -> Callable[..., None]:
    for option in reversed(
        [
            click.option(
                "--mode",
                type=click.Choice(["T1", "T2", "AUT", "EX"]),
                default="EX",
                show_default=True,
                help="The operating mode ($MODE_OP).",
            ),
            click.option(
                "--drives-off", is_flag=True, help="Fault: the drives are off ($PERI_RDY FALSE)."
            ),
            click.option(
                "--no-ack", is_flag=True, help="Fault: the KRL loop never acknowledges a move."
            ),
        ]
    ):
        f = option(f)
    return _twin_options(f)


def _serve_kuka(interface: str, **o: Any) -> None:
    from cellcal.families import EkiTwin, KvpTwin, krc_for_cell

    config, cell = simulated_cell_of(o["config_path"], o["seed"])
    controller = krc_for_cell(list(config.robot.home_deg), cell, o["time_scale"])
    controller.faults.mode = f"#{o['mode']}"
    controller.faults.drives_on = not o["drives_off"]
    controller.faults.no_ack = o["no_ack"]
    twin = KvpTwin(controller) if interface == "KUKAVARPROXY" else EkiTwin(controller)
    serve_until_signal(twin, o["listen"], f"mock KUKA controller ({interface}) serving on {{}}")


@click.command("kuka-kvp")
@_kuka_options
def mock_kuka_kvp(**options: Any) -> None:
    """A KUKA controller running cellcal's KRL loop behind KUKAVARPROXY (docs/robots.md):
    the simulated cell's robot, served until Ctrl-C or SIGTERM; prints HOST:PORT."""
    _serve_kuka("KUKAVARPROXY", **options)


@click.command("kuka-eki")
@_kuka_options
def mock_kuka_eki(**options: Any) -> None:
    """A KUKA controller running CellCalEki, the EthernetKRL channel's server
    (docs/robots.md): the simulated cell's robot, served until Ctrl-C or SIGTERM; prints
    HOST:PORT."""
    _serve_kuka("EthernetKRL", **options)


@click.command("abb-rws")
@_twin_options
@click.option(
    "--opmode",
    type=click.Choice(["AUTO", "MANR", "MANF"]),
    default="AUTO",
    show_default=True,
    help="The operating mode (rw/panel/opmode).",
)
@click.option("--motors-off", is_flag=True, help="Fault: the motors are off.")
@click.option("--stopped", is_flag=True, help="Fault: RAPID is not running.")
@click.option(
    "--mastership-held", is_flag=True, help="Fault: another client holds RAPID mastership."
)
def mock_abb_rws(
    listen: str,
    config_path: str | None,
    seed: int | None,
    time_scale: float,
    opmode: str,
    motors_off: bool,
    stopped: bool,
    mastership_held: bool,
) -> None:
    """An ABB IRC5 running cellcal's RAPID module behind Robot Web Services 1.0
    (docs/robots.md): the simulated cell's robot, served until Ctrl-C or SIGTERM; prints
    http://HOST:PORT. The user is ABB's factory user."""
    from cellcal.families import RwsTwin, krc_for_cell

    config, cell = simulated_cell_of(config_path, seed)
    twin = RwsTwin(
        krc_for_cell(list(config.robot.home_deg), cell, time_scale), system_name=cell.model.name
    )
    twin.faults.opmode = opmode
    twin.faults.motors_on = not motors_off
    twin.faults.running = not stopped
    twin.faults.mastership_held = mastership_held
    serve_until_signal(twin, listen, "mock ABB controller (RWS 1.0) on {}", scheme="http://")


@click.command("fanuc-rmi")
@_cell_options(
    click.option(
        "--host",
        required=True,
        help="Loopback address to bind (RMI's connection port 16001 and the session's 16002).",
    )
)
@click.option("--tp-enabled", is_flag=True, help="Fault: the teach pendant is enabled.")
@click.option("--servo-off", is_flag=True, help="Fault: the servo is off (ServoReady 0).")
@click.option("--single-step", is_flag=True, help="Fault: single step mode.")
def mock_fanuc_rmi(
    host: str,
    config_path: str | None,
    seed: int | None,
    time_scale: float,
    tp_enabled: bool,
    servo_off: bool,
    single_step: bool,
) -> None:
    """A FANUC controller with the Remote Motion Interface (docs/robots.md): the simulated
    cell's robot on HOST:16001 (the session on HOST:16002), served until Ctrl-C or
    SIGTERM; prints HOST:16001."""
    from cellcal.families import RmiTwin, krc_for_cell

    config, cell = simulated_cell_of(config_path, seed)
    twin = RmiTwin(
        krc_for_cell(list(config.robot.home_deg), cell, time_scale), time_scale=time_scale
    )
    twin.faults.tp_enabled = tp_enabled
    twin.faults.servo_off = servo_off
    twin.faults.single_step = single_step
    serve_until_signal(twin, f"{host}:16001", "mock FANUC controller (RMI) on {}")


@click.command("yaskawa-hses")
@_twin_options
@click.option(
    "--pulses-per-degree",
    help="The encoder pulses per degree of each axis, comma-separated (default: the "
    "configuration's, when its robot is a yaskawa-hses one).",
)
@click.option("--teach", is_flag=True, help="Fault: the controller is in TEACH.")
@click.option("--no-remote", is_flag=True, help="Fault: command remote is not set.")
@click.option("--servo-locked", is_flag=True, help="Fault: the servo cannot be turned on.")
@click.option(
    "--lose-every",
    type=click.IntRange(0),
    default=0,
    help="Fault: every N-th request datagram is lost.",
)
@click.option(
    "--duplicate-every",
    type=click.IntRange(0),
    default=0,
    help="Fault: every N-th answer is sent twice.",
)
def mock_yaskawa_hses(
    listen: str,
    config_path: str | None,
    seed: int | None,
    time_scale: float,
    pulses_per_degree: str | None,
    teach: bool,
    no_remote: bool,
    servo_locked: bool,
    lose_every: int,
    duplicate_every: int,
) -> None:
    """A Yaskawa YRC1000's High-Speed Ethernet Server (docs/robots.md): the simulated
    cell's robot on UDP HOST:PORT, served until Ctrl-C or SIGTERM; prints HOST:PORT."""
    from cellcal.families import HsesTwin, krc_for_cell

    config, cell = simulated_cell_of(config_path, seed)
    ppd = _pulses_per_degree(pulses_per_degree, config)
    twin = HsesTwin(krc_for_cell(list(config.robot.home_deg), cell, time_scale), ppd)
    twin.faults.teach = teach
    twin.faults.remote = not no_remote
    twin.faults.servo_locked = servo_locked
    twin.faults.lose_every = lose_every
    twin.faults.duplicate_every = duplicate_every
    serve_until_signal(twin, listen, "mock Yaskawa controller (HSES, UDP) on {}")


def _pulses_per_degree(text: str | None, config: Any) -> list[float]:
    from cellcal.drivers.yaskawa_hses import checked_pulses_per_degree
    from cellcal.errors import InputError

    if text is None:
        configured = getattr(config.robot, "pulses_per_degree", None)
        if configured is None:
            raise InputError(
                "--pulses-per-degree: the configuration's robot is not a yaskawa-hses one: "
                "give the pulses per degree of each axis"
            )
        return list(configured)
    try:
        return checked_pulses_per_degree([float(v) for v in text.split(",")])
    except ValueError as exc:
        raise InputError(f"--pulses-per-degree {text}: {exc}") from None
