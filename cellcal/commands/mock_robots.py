"""``cellcal mock kuka-kvp``: the twins of the robot controllers reached through their
own interfaces (docs/robots.md), each serving the simulated cell's robot as the
controller running cellcal's program would."""

from __future__ import annotations

import click

from cellcal.commands.mock import _host_port, simulated_cell_of, wait_for_signal
from cellcal.commands.output import SEED, TIME_SCALE
from cellcal.errors import InputError


@click.command("kuka-kvp")
@click.option(
    "--listen", required=True, help="TCP address HOST:PORT (a 127.0.0.x address for tests)."
)
@click.option(
    "--config",
    "config_path",
    help='Cell configuration with driver = "kuka-kvp" (default: the bundled cell\'s robot).',
)
@click.option("--seed", type=SEED, help="Seed of the simulated truth.")
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=1.0,
    show_default=True,
    help="Wall seconds per second of motion.",
)
@click.option(
    "--mode",
    type=click.Choice(["T1", "T2", "AUT", "EX"]),
    default="EX",
    show_default=True,
    help="The operating mode ($MODE_OP).",
)
@click.option("--drives-off", is_flag=True, help="Fault: the drives are off ($PERI_RDY FALSE).")
@click.option("--no-ack", is_flag=True, help="Fault: the KRL loop never acknowledges a move.")
def mock_kuka_kvp(
    listen: str,
    config_path: str | None,
    seed: int | None,
    time_scale: float,
    mode: str,
    drives_off: bool,
    no_ack: bool,
) -> None:
    """A KUKA controller running cellcal's KRL loop behind KUKAVARPROXY (docs/robots.md):
    the simulated cell's robot, served until Ctrl-C or SIGTERM; prints HOST:PORT."""
    from cellcal.drivers.kuka_kvp import KukaKvpOptions
    from cellcal.families import KvpTwin, krc_for

    config, cell = simulated_cell_of(config_path, seed)
    robot = config.robot
    options = (
        robot
        if isinstance(robot, KukaKvpOptions)
        else KukaKvpOptions(model=robot.model, home_deg=list(robot.home_deg))
    )
    controller = krc_for(options, cell, time_scale)
    controller.faults.mode = f"#{mode}"
    controller.faults.drives_on = not drives_off
    controller.faults.no_ack = no_ack
    twin = KvpTwin(controller)
    try:
        host, port = twin.start(*_host_port(listen))
    except (OSError, RuntimeError) as exc:
        raise InputError(f"--listen {listen}: cannot listen ({exc})") from None
    try:
        click.echo(f"mock KUKA controller (KUKAVARPROXY) serving on {host}:{port}", err=True)
        click.echo(f"{host}:{port}")
        wait_for_signal()
    finally:
        twin.stop()
