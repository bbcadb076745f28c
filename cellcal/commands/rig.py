"""``cellcal rig …``: the photogrammetry rig's own jobs (measure the target in images)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from cellcal.calib.camera_rig import Rig, Target
from cellcal.calib.rig_measurement import TargetMeter
from cellcal.calib.target_pose import TargetPose
from cellcal.commands.output import jsonable, print_json
from cellcal.errors import InputError, MeasurementError
from cellcal.imagefiles import image_option, read_image, set_folders, set_images
from cellcal.photofiles import read_rig, read_target


@click.group()
def rig() -> None:
    """The photogrammetry rig: measure the marker target in camera images."""


def _pose_json(pose: TargetPose) -> dict[str, Any]:
    return {
        "xyz_mm": pose.xyz_mm,
        "cov_mm2": pose.cov_mm2,
        "T_rig_target": pose.T_rig_target,
        "cameras": list(pose.cameras),
        "markers": pose.markers,
        "reprojection_rms_px": pose.reprojection_rms_px,
        "dropped": list(pose.dropped),
    }


def _pose_line(pose: TargetPose) -> str:
    x, y, z = pose.xyz_mm
    sx, sy, sz = (pose.cov_mm2.diagonal()) ** 0.5
    dropped = f"; left out: {', '.join(pose.dropped)}" if pose.dropped else ""
    return (
        f"x {x:.4f}  y {y:.4f}  z {z:.4f} mm  (1σ {sx:.4f} {sy:.4f} {sz:.4f} mm; "
        f"{len(pose.cameras)} cameras {','.join(pose.cameras)}, {pose.markers} markers, "
        f"{pose.reprojection_rms_px:.3f} px RMS{dropped})"
    )


def _images(paths: dict[str, Path], rig_: Rig) -> dict[str, Any]:
    known = {c.name for c in rig_.cameras}
    unknown = sorted(set(paths) - known)
    if unknown:
        raise InputError(f"--image: {', '.join(unknown)} not a camera of rig {rig_.name!r}")
    out = {}
    for cam, path in paths.items():
        img = read_image(path)
        c = rig_.camera(cam)
        if img.shape[:2] != (c.height, c.width):
            raise InputError(
                f"{path}: {img.shape[1]}×{img.shape[0]} px, but camera {cam} is "
                f"{c.width}×{c.height} in the rig file"
            )
        out[cam] = img
    return out


@rig.command("measure")
@click.option("--rig", "rig_path", required=True, help="The rig file (TOML).")
@click.option("--target", "target_path", required=True, help="The target file (TOML).")
@click.option("--image", "image_specs", multiple=True, help="CAM=PATH, once per camera.")
@click.option("--sets", "sets_dir", help="A directory: one folder per set, <camera>.png in each.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (one object per set).")
def measure(
    rig_path: str,
    target_path: str,
    image_specs: tuple[str, ...],
    sets_dir: str | None,
    as_json: bool,
) -> None:
    """Measure the target from one set of images (one per camera) or from many sets.

    Prints the target's reference point in the rig frame (mm) with its 1σ, the cameras
    that saw it, the markers used and the reprojection RMS. With --sets, a set that fewer
    than two cameras see gives its reason and the command goes on.
    """
    if bool(image_specs) == bool(sets_dir):
        raise InputError("give either --image CAM=PATH (once per camera) or --sets DIR")
    rig_ = read_rig(rig_path)
    target: Target = read_target(target_path)
    meter = TargetMeter(rig_, target)
    if image_specs:
        pose = meter.measure(_images(image_option(image_specs), rig_))
        if as_json:
            print_json(_pose_json(pose))
        else:
            click.echo(f"rig measure: target {target.name!r} in rig {rig_.name!r}")
            click.echo(_pose_line(pose))
        return
    cameras = tuple(c.name for c in rig_.cameras)
    measured = 0
    folders = set_folders(sets_dir or "")
    for folder in folders:
        meter.reset()  # sets may be of different poses: each is measured on its own
        try:
            pose = meter.measure(_images(set_images(folder, cameras), rig_))
        except MeasurementError as exc:
            line: dict[str, Any] = {"set": folder.name, "error": str(exc)}
            click.echo(json.dumps(line) if as_json else f"{folder.name}: {exc}")
            continue
        measured += 1
        if as_json:
            click.echo(json.dumps(jsonable({"set": folder.name, **_pose_json(pose)})))
        else:
            click.echo(f"{folder.name}: {_pose_line(pose)}")
    if measured == 0:
        raise MeasurementError(f"no set in {sets_dir} measured the target")
