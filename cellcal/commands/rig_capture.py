"""``cellcal rig capture`` (grab image sets from the configured cameras) and ``cellcal
mock cameras`` (serve the simulated cell's cameras as GigE Vision devices)."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from cellcal.commands.output import SEED
from cellcal.config import CellConfig
from cellcal.errors import DeviceError, InputError
from cellcal.extras import require

if TYPE_CHECKING:
    from cellcal.drivers.photogrammetry import CameraRigOptions

HOSTS = re.compile(r"^127\.0\.0\.(\d{1,3})-(\d{1,3})$")


def _rig_sensor(config: CellConfig, name: str | None, source: str) -> CameraRigOptions:
    """The configuration's photogrammetry sensor (the one named, else the first)."""
    from cellcal.drivers.photogrammetry import CameraRigOptions

    rigs = [s for s in config.sensor if s.kind == "photogrammetry"]
    if name is not None:
        rigs = [s for s in rigs if s.name == name]
    if not rigs or not isinstance(rigs[0], CameraRigOptions):
        what = f"no photogrammetry sensor {name!r}" if name else "no photogrammetry sensor"
        raise InputError(f"{source}: {what}")
    return rigs[0]


@click.command("capture")
@click.option("--config", "config_path", help="Cell configuration (with --mock: optional).")
@click.option("--out", "out_dir", required=True, help="Folder for the sets (created).")
@click.option("--sets", "n_sets", type=click.IntRange(1, 100000), default=1, show_default=True)
@click.option("--sensor", default=None, help="Which photogrammetry sensor (default: the first).")
@click.option(
    "--mock",
    is_flag=True,
    help="Grab from the simulated cell's camera twins (the bundled cell without --config).",
)
@click.option(
    "--board",
    "board_path",
    help="With --mock: the cameras see this ChArUco board, a new pose every set.",
)
@click.option("--seed", type=SEED, help="With --mock: the seed of the simulated truth and noise.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object per set.")
def rig_capture(
    config_path: str | None,
    out_dir: str,
    n_sets: int,
    sensor: str | None,
    mock: bool,
    board_path: str | None,
    seed: int | None,
    as_json: bool,
) -> None:
    """Grab synchronised image sets from the configured cameras: one folder per set,
    ``<camera>.png`` in each (what ``rig measure --sets`` and the ``files`` backend read).

    With --mock the cameras are the simulated cell's twins, reached through the
    configured driver: they see the flange's target where the simulated robot holds it
    (at home), or with --board a calibration board held up at a new pose every set (the
    views `rig calibrate` takes).
    """
    from cellcal.commands.run import cell_config

    require("cellcal rig capture", "cv2")
    if not mock and (board_path is not None or seed is not None):
        raise InputError("--board and --seed are for --mock (the simulated cell's cameras)")
    if config_path is None and not mock:
        raise InputError("--config FILE is needed (or --mock for the simulated cell)")
    config, source = cell_config(config_path, mock)
    options = _rig_sensor(config, sensor, source)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out}: {exc.strerror}") from None
    if mock:
        from cellcal.families import mock_rig

        twin = mock_rig(config, options, board_path, n_sets, seed)
        try:
            _grab(twin.cameras, out, n_sets, as_json, twin.announce)
        finally:
            twin.stop()
        return
    from cellcal.drivers.cameras.backends import rig_class

    _grab(rig_class(options.capture.backend).from_options(options.capture), out, n_sets, as_json)


def _grab(
    cameras: Any,
    out: Path,
    n_sets: int,
    as_json: bool,
    announce: Callable[[int], None] | None = None,
) -> None:
    from cellcal.files.images import write_image

    cameras.connect()
    try:
        for k in range(1, n_sets + 1):
            if announce is not None:
                announce(k - 1)
            frames = cameras.grab()
            folder = out / f"set-{k:04d}"
            try:
                folder.mkdir(exist_ok=True)
            except OSError as exc:  # a file, FIFO or device of that name
                raise InputError(
                    f"{folder}: cannot make the set's folder ({exc.strerror})"
                ) from None
            for name, frame in frames.frames.items():
                write_image(folder / f"{name}.png", frame.image)
            record = {
                "set": folder.name,
                "frames": {n: f.frame_id for n, f in frames.frames.items()},
                "retries": frames.retries,
                "lost": frames.lost,
            }
            if as_json:
                click.echo(json.dumps(record))
            else:
                lost = "; ".join(f"{c} lost ({why})" for c, why in frames.lost.items())
                line = f"{folder}: {len(frames.frames)} of {len(cameras.cameras)} cameras"
                click.echo(line + (f"; {lost}" if lost else ""))
    finally:
        cameras.close()


def _hosts(text: str, n: int) -> int:
    """``127.0.0.A-B`` → A, checked against the rig's number of cameras."""
    m = HOSTS.match(text)
    if m is None:
        raise InputError(f"--hosts {text!r}: expected 127.0.0.A-B (a range of loopback hosts)")
    first, last = int(m.group(1)), int(m.group(2))
    if not 2 <= first <= last <= 254:
        raise InputError(f"--hosts {text!r}: hosts 2..254, first ≤ last")
    if last - first + 1 != n:
        raise InputError(f"--hosts {text!r}: {last - first + 1} addresses for {n} cameras")
    return first


@click.command("cameras")
@click.option("--rig", "rig_path", required=True, help="Rig file (the cameras to serve).")
@click.option("--target", "target_path", help="Target file (what they see on the flange).")
@click.option("--board", "board_path", help="Board file: they see this ChArUco board instead.")
@click.option(
    "--views",
    type=click.IntRange(1, 10000),
    default=20,
    show_default=True,
    help="With --board: the board's poses, one a set, in turn.",
)
@click.option("--hosts", default="127.0.0.2-5", show_default=True, help="Their addresses.")
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled simulated cell)."
)
@click.option("--seed", type=SEED, help="Seed of the simulated truth and noise.")
def mock_cameras(
    rig_path: str,
    target_path: str | None,
    board_path: str | None,
    views: int,
    hosts: str,
    config_path: str | None,
    seed: int | None,
) -> None:
    """Serve the simulated cell's cameras as GigE Vision devices (Aravis's fake camera)
    in a network namespace of their own, until Ctrl-C or SIGTERM: each frame rendered
    from where the simulated robot holds the target (at home), or with --board a
    ChArUco board held up at --views poses in turn (a new pose each set)."""
    require("cellcal mock cameras", "cv2")
    from cellcal.commands.mock import simulated_cell_of, wait_for_signal
    from cellcal.families import BoardScene, GigECameraTwin, RigScene, RigTruth
    from cellcal.files.photogrammetry import read_board, read_rig, read_target

    if (target_path is None) == (board_path is None):
        raise InputError("give either --target FILE (the flange's target) or --board FILE")
    rig = read_rig(rig_path)
    first = _hosts(hosts, len(rig.cameras))
    config, cell = simulated_cell_of(config_path, seed)
    sensor = _rig_sensor(config, None, config_path or "the bundled cell")
    truth = RigTruth.of(cell, sensor.name)
    scene: RigScene | BoardScene
    if board_path is not None:
        board = read_board(board_path)
        scene = BoardScene(rig, board, views, truth.seed, truth.blur_px, truth.noise_grey)
    else:
        assert target_path is not None
        scene = RigScene(truth, rig, read_target(target_path), lambda: cell.q)
    cam = rig.cameras[0]
    twin = GigECameraTwin(
        [c.name for c in rig.cameras],
        scene.image,
        width=cam.width,
        height=cam.height,
        first_address=first,
        writer=scene.write,
    )
    try:
        twin.start()
    except DeviceError as exc:
        raise DeviceError(f"mock cameras: {exc}") from None
    try:
        for name, address in twin.addresses.items():
            click.echo(f"camera {name}: GigE Vision at {address}")
        click.echo(
            f"network namespace: {twin.netns} (pid {os.getpid()}); e.g. nsenter "
            f"--net={twin.netns} arv-tool-0.8 -a {twin.addresses[rig.cameras[0].name]} "
            "control DeviceModelName",
        )
        click.echo("serving; Ctrl-C to stop", err=True)
        wait_for_signal()
    finally:
        twin.stop()
