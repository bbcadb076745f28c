"""``cellcal mock …``: the simulated cell's devices as protocol-level servers."""

from __future__ import annotations

import signal
import threading
from types import FrameType

import click

from cellcal.config import load_config
from cellcal.errors import InputError
from cellcal.modelfiles import load_model


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(f"--listen {text!r}: expected HOST:PORT, e.g. 127.0.0.5:5555")
    return host, int(port)


def _wait_for_signal() -> None:
    done = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        done.set()

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, on_signal)
    while not done.wait(0.5):
        pass


@click.group()
def mock() -> None:
    """Serve the simulated cell's devices over their real wire protocols."""


@mock.command("tracker")
@click.option("--listen", help="TCP address HOST:PORT (a 127.0.0.x address for tests).")
@click.option("--pty", "use_pty", is_flag=True, help="Serve on a pseudo-terminal instead.")
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled simulated cell)."
)
@click.option("--sensor", default=None, help="Which laser-tracker sensor of the configuration.")
@click.option("--seed", type=int, help="Seed of the simulated truth and noise.")
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
@click.option("--reply-delay", type=float, default=0.0, help="Fault: seconds before every reply.")
@click.option("--drop-after", type=int, help="Fault: drop the connection after N lines.")
@click.option(
    "--time-scale",
    type=float,
    default=1.0,
    show_default=True,
    help="Wall seconds per tracker second (pacing of points).",
)
def mock_tracker(
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
    """A laser tracker of the simulated cell, speaking the tracker line protocol."""
    from cellcal.commands.run import bundled_mock_cell
    from cellcal.mocks.simulated_cell import SimulatedCell
    from cellcal.mocks.tracker_server import MockTracker, TrackerFaults

    if (listen is None) == (not use_pty):
        raise InputError("give --listen HOST:PORT or --pty")
    config = load_config(config_path) if config_path else bundled_mock_cell()[0]
    trackers = [s.name for s in config.sensor if s.kind == "laser-tracker"]
    name = sensor or (trackers[0] if trackers else None)
    if name is None or name not in trackers:
        raise InputError(
            f"no laser-tracker sensor {sensor!r} in the configuration ({', '.join(trackers)})"
        )
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed)
    faults = TrackerFaults(
        beam_break_after=beam_break_after,
        beam_breaks=beam_breaks,
        garbage_every=garbage_every,
        event_every=event_every,
        reply_delay_s=reply_delay,
        drop_after_lines=drop_after,
    )
    server = MockTracker(cell.target(name), faults=faults, time_scale=time_scale)
    with server:
        if use_pty:
            where = server.start_pty()
        else:
            assert listen is not None
            host, port = server.start_tcp(*_host_port(listen))
            where = f"socket://{host}:{port}"
        click.echo(f"mock tracker {name!r} of {config.name!r} serving on {where}", err=True)
        click.echo(where)
        _wait_for_signal()
