"""``cellcal rig capture`` (grab image sets from the configured cameras) and ``cellcal
mock cameras`` (serve the simulated cell's cameras as GigE Vision devices)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import click

from cellcal.commands.output import SEED
from cellcal.config import CellConfig, load_config
from cellcal.drivers.photogrammetry import CameraRigOptions
from cellcal.errors import DeviceError, InputError

HOSTS = re.compile(r"^127\.0\.0\.(\d{1,3})-(\d{1,3})$")


def _rig_sensor(config: CellConfig, name: str | None, source: str) -> CameraRigOptions:
    """The configuration's photogrammetry sensor (the one named, else the first)."""
    rigs = [s for s in config.sensor if s.kind == "photogrammetry"]
    if name is not None:
        rigs = [s for s in rigs if s.name == name]
    if not rigs or not isinstance(rigs[0], CameraRigOptions):
        what = f"no photogrammetry sensor {name!r}" if name else "no photogrammetry sensor"
        raise InputError(f"{source}: {what}")
    return rigs[0]


@click.command("capture")
@click.option("--config", "config_path", required=True, help="Cell configuration.")
@click.option("--out", "out_dir", required=True, help="Folder for the sets (created).")
@click.option("--sets", "n_sets", type=click.IntRange(1, 100000), default=1, show_default=True)
@click.option("--sensor", default=None, help="Which photogrammetry sensor (default: the first).")
@click.option("--json", "as_json", is_flag=True, help="One JSON object per set.")
def rig_capture(
    config_path: str, out_dir: str, n_sets: int, sensor: str | None, as_json: bool
) -> None:
    """Grab synchronised image sets from the configured cameras: one folder per set,
    ``<camera>.png`` in each (what ``rig measure --sets`` and the ``files`` backend read).
    """
    from cellcal.drivers.cameras import rig_class
    from cellcal.imagefiles import write_image

    config = load_config(config_path)
    options = _rig_sensor(config, sensor, config_path)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out}: {exc.strerror}") from None
    cameras = rig_class(options.capture.backend).from_options(options.capture)
    cameras.connect()
    try:
        for k in range(1, n_sets + 1):
            frames = cameras.grab()
            folder = out / f"set-{k:04d}"
            folder.mkdir(exist_ok=True)
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
@click.option("--target", "target_path", required=True, help="Target file (what they see).")
@click.option("--hosts", default="127.0.0.2-5", show_default=True, help="Their addresses.")
@click.option(
    "--config", "config_path", help="Cell configuration (default: the bundled simulated cell)."
)
@click.option("--seed", type=SEED, help="Seed of the simulated truth and noise.")
def mock_cameras(
    rig_path: str, target_path: str, hosts: str, config_path: str | None, seed: int | None
) -> None:
    """Serve the simulated cell's cameras as GigE Vision devices (Aravis's fake camera)
    in a network namespace of their own, each frame rendered from where the simulated
    robot holds the target (at home), until Ctrl-C or SIGTERM."""
    from cellcal.commands.mock import simulated_cell_of, wait_for_signal
    from cellcal.mocks.gige_cameras import GigECameraTwin
    from cellcal.mocks.rig_twin import RigScene, RigTruth
    from cellcal.photofiles import read_rig, read_target

    rig, target = read_rig(rig_path), read_target(target_path)
    first = _hosts(hosts, len(rig.cameras))
    config, cell = simulated_cell_of(config_path, seed)
    sensor = _rig_sensor(config, None, config_path or "the bundled cell")
    scene = RigScene(RigTruth.of(cell, sensor.name), rig, target, lambda: cell.q)
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
