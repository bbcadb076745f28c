"""``cellcal rig …``: the photogrammetry rig's own jobs (measure the target in images)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
import numpy as np

from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.calib.photogrammetry.rig_calibration import (
    RigCalibration,
    RigCalibrationOptions,
    calibrate_rig,
)
from cellcal.calib.photogrammetry.rig_measurement import TargetMeter
from cellcal.calib.photogrammetry.target_pose import TargetPose
from cellcal.commands.output import jsonable, print_json
from cellcal.errors import AcceptanceError, InputError, MeasurementError
from cellcal.files.images import (
    Unreadable,
    image_option,
    load_views,
    read_camera_image,
    read_set,
    set_folders,
    stray_images,
)
from cellcal.files.outputs import check_output_file
from cellcal.files.photogrammetry import read_board, read_rig, read_target, write_rig


@click.group()
def rig() -> None:
    """The photogrammetry rig: calibrate it from ChArUco views, measure the target."""


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
        c = rig_.camera(cam)
        out[cam] = read_camera_image(path, cam, (c.width, c.height))
    return out


def _refuse_stray_images(folders: list[Path], rig_: Rig, sets_dir: str) -> None:
    """A ``<name>.png`` in a set that is no camera of the rig: the sets are of another rig."""
    stray = stray_images(folders, (c.name for c in rig_.cameras))
    if stray:
        more = f"; {len(stray) - 1} more such files in {sets_dir}" if len(stray) > 1 else ""
        raise InputError(
            f"{stray[0]}: {stray[0].stem!r} is not a camera of rig {rig_.name!r} "
            f"({', '.join(c.name for c in rig_.cameras)}){more}"
        )


def _left_out(unreadable: list[Unreadable]) -> str:
    """The text line's note of a set's unreadable images, or ""."""
    if not unreadable:
        return ""
    return " (" + "; ".join(f"{u.camera} left out: {u.reason}" for u in unreadable) + ")"


def _some(items: list[str], n: int, sep: str) -> str:
    shown = sep.join(items[:n])
    return shown if len(items) <= n else f"{shown}{sep}and {len(items) - n} more"


def _batch_summary(
    sets: int, measured: int, unreadable: list[tuple[str, Unreadable]], skipped: list[str]
) -> str:
    """One line: how many sets were measured, the images that could not be used, the sets
    skipped."""
    parts = [f"rig measure: {measured} of {sets} sets measured"]
    if unreadable:
        files = [f"{name}/{u.path.name}: {u.reason}" for name, u in unreadable]
        k = len(unreadable)
        parts.append(f"{k} image{'s' * (k != 1)} unreadable ({_some(files, 3, '; ')})")
    if skipped:
        k = len(skipped)
        parts.append(f"{k} set{'s' * (k != 1)} skipped ({_some(skipped, 5, ', ')})")
    return "; ".join(parts)


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
    that saw it, the markers used and the reprojection RMS.

    With --sets, every set is measured on its own and printed. An image that cannot be
    used (truncated, not an image, empty, of another size than the rig's camera) is named
    on stderr and in its set's line, and the set measured with the other cameras; a set
    fewer than two cameras see gives its reason. After the last set, exit 0 if every set
    was measured from all its images, else one summary line on stderr and exit 2.
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
    folders = set_folders(sets_dir or "")
    _refuse_stray_images(folders, rig_, sets_dir or "")
    sizes = {c.name: (c.width, c.height) for c in rig_.cameras}
    measured = 0
    skipped: list[str] = []
    unreadable_all: list[tuple[str, Unreadable]] = []
    for folder in folders:
        images, unreadable = read_set(folder, sizes)
        for u in unreadable:
            click.echo(
                f"cellcal: rig measure: {u.path}: {u.reason}; {u.camera} left out of {folder.name}",
                err=True,
            )
        unreadable_all += [(folder.name, u) for u in unreadable]
        bad = [{"camera": u.camera, "path": str(u.path), "error": u.reason} for u in unreadable]
        try:
            if not images:
                raise MeasurementError(
                    "no image of the rig's cameras could be read"
                    if unreadable
                    else f"no image of the rig's cameras ({', '.join(sizes)}; <camera>.png)"
                )
            pose = meter.measure_next(images)  # followed from the last set if still there
        except MeasurementError as exc:
            skipped.append(folder.name)
            line: dict[str, Any] = {"set": folder.name, "error": str(exc), "unreadable": bad}
            click.echo(
                json.dumps(line) if as_json else f"{folder.name}: {exc}{_left_out(unreadable)}"
            )
            continue
        measured += 1
        if as_json:
            line = {"set": folder.name, **_pose_json(pose), "unreadable": bad}
            click.echo(json.dumps(jsonable(line)))
        else:
            click.echo(f"{folder.name}: {_pose_line(pose)}{_left_out(unreadable)}")
    if skipped or unreadable_all:
        raise MeasurementError(_batch_summary(len(folders), measured, unreadable_all, skipped))


def _calibration_json(cal: RigCalibration) -> dict[str, Any]:
    h = cal.holdout
    return {
        "rig": cal.rig.name,
        "rms_px": cal.rms_px,
        "sigma_px": cal.sigma_px,
        "fit_views": len(cal.fit_views),
        "cameras": [
            {
                "name": c.name,
                "views": c.views,
                "corners": c.corners,
                "rejected": c.rejected,
                "unmeasured": c.unmeasured,
                "reprojection_rms_px": c.rms_px,
                "sigma_fx_px": c.sigma_fx_px,
                "sigma_fy_px": c.sigma_fy_px,
                "sigma_cx_px": c.sigma_cx_px,
                "sigma_cy_px": c.sigma_cy_px,
                "sigma_position_mm": c.sigma_position_mm,
                "sigma_rotation_deg": c.sigma_rotation_deg,
            }
            for c in cal.cameras
        ],
        "holdout": None
        if h is None
        else {
            "views": list(h.views),
            "reprojection_rms_px": h.reprojection_rms_px,
            "lengths": h.lengths,
            "length_rms_mm": h.length_rms_mm,
            "length_max_mm": h.length_max_mm,
        },
        "suspect_cameras": list(cal.suspect_cameras),
        "warnings": list(cal.warnings),
        "verdict": "fails" if cal.failures else "passes",
        "failures": list(cal.failures),
    }


@rig.command("calibrate")
@click.option("--board", "board_path", required=True, help="The ChArUco board file (TOML).")
@click.option(
    "--views", "views_dir", required=True, help="One folder per view, <camera>.png in each."
)
@click.option("--out", "out_path", required=True, help="The rig file to write (TOML).")
@click.option("--name", default="cell-rig", show_default=True, help="The rig's name.")
@click.option("--fix-k3", is_flag=True, help="Keep k3 at 0 (lenses with little distortion).")
@click.option("--fix-tangential", is_flag=True, help="Keep p1 and p2 at 0.")
@click.option(
    "--max-length-error",
    "max_length_mm",
    type=float,
    default=RigCalibrationOptions.max_length_rms_mm,
    show_default=True,
    help="Largest RMS error (mm) of the held-out board lengths for a rig that passes.",
)
@click.option(
    "--accept",
    is_flag=True,
    help="Write the rig even if a check fails (the failures are recorded in the file).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def calibrate(
    board_path: str,
    views_dir: str,
    out_path: str,
    name: str,
    fix_k3: bool,
    fix_tangential: bool,
    max_length_mm: float,
    accept: bool,
    as_json: bool,
) -> None:
    """Calibrate the camera rig (intrinsics and extrinsics) from ChArUco views.

    The board's corners are measured from their edges with each camera's first
    calibration, then every camera's intrinsics and pose are fitted together by bundle
    adjustment; the rig frame is the first camera's. Every fifth view is held out and
    measured with the result: its reprojection RMS and the board's known lengths, with a
    verdict. A camera whose views are shifted as a whole (it moved while the views were
    taken), or a held-out check that fails, is refused with exit 3 and no rig file is
    written, unless --accept is given.
    """
    if not max_length_mm > 0:
        raise InputError(
            f"--max-length-error: expected a positive length in mm, got {max_length_mm}"
        )
    check_output_file(out_path)  # before the bundle adjustment: a device or FIFO is refused
    board = read_board(board_path)
    click.echo(f"rig calibrate: reading the views in {views_dir}…", err=True)
    views = load_views(views_dir)
    click.echo(
        f"rig calibrate: {len(views.views)} views of {len(views.cameras)} cameras: finding "
        "the board, measuring its corners from their edges, adjusting the bundle…",
        err=True,
    )
    options = RigCalibrationOptions(
        fix_k3=fix_k3, fix_tangential=fix_tangential, max_length_rms_mm=max_length_mm
    )
    cal = calibrate_rig(
        board, views.cameras, list(views.views), options, view_names=views.names, name=name
    )
    if cal.failures and not accept:
        raise AcceptanceError("rig calibration", "; ".join(cal.failures))
    write_rig(out_path, cal.rig, accepted_despite=cal.failures)
    if as_json:
        print_json(_calibration_json(cal))
        return
    click.echo(
        f"rig calibrate: {len(cal.rig.cameras)} cameras from {len(cal.fit_views)} views, "
        f"reprojection RMS {cal.rms_px:.3f} px; rig file {out_path}"
    )
    for c in cal.cameras:
        sp = np.linalg.norm(c.sigma_position_mm)
        click.echo(
            f"  {c.name}: {c.views} views, {c.corners} corners ({c.rejected} outliers, "
            f"{c.unmeasured} unmeasurable left out), "
            f"RMS {c.rms_px:.3f} px; 1σ fx {c.sigma_fx_px:.2f} cx {c.sigma_cx_px:.2f} "
            f"cy {c.sigma_cy_px:.2f} px, position {sp:.3f} mm, "
            f"rotation {np.linalg.norm(c.sigma_rotation_deg):.4f}°"
        )
    if cal.holdout is not None:
        h = cal.holdout
        click.echo(
            f"  held out {len(h.views)} views: reprojection RMS {h.reprojection_rms_px:.3f} px; "
            f"{h.lengths} board lengths: RMS error {h.length_rms_mm:.4f} mm, "
            f"max {h.length_max_mm:.4f} mm"
        )
    for w in cal.warnings:
        click.echo(f"  warning: {w}")
    if cal.failures:
        click.echo(f"  verdict: fails, written with --accept ({'; '.join(cal.failures)})")
    elif cal.holdout is not None:
        click.echo(
            f"  verdict: passes (held-out lengths within {options.max_length_rms_mm:g} mm RMS, "
            "reprojection like the fit's)"
        )
    else:
        click.echo("  verdict: not checked (no view held out)")
