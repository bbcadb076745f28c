"""The first steps of a rig calibration, camera by camera: the input checks, the views
in which no camera found the board, each camera's own intrinsics (``cv2.calibrateCamera``
on its views) and its corners measured again from their edges with them
(:class:`~cellcal.calib.photogrammetry.board_corners.CornerMeter`), and the calibration's options.

Pure numerics: images (numpy arrays) in; :mod:`cellcal.calib.photogrammetry.rig_calibration`
does the
rest.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.board_corners import (
    CornerDetection,
    CornerMeter,
    mirrored_count,
    shows_mirrored,
)
from cellcal.calib.photogrammetry.bundle import pose
from cellcal.calib.photogrammetry.camera_rig import Board
from cellcal.errors import InputError, MeasurementError

Image = NDArray[Any]


@dataclass(frozen=True)
class RigCalibrationOptions:
    """Choices of the calibration: distortion terms held at zero, detection and
    outlier thresholds, and which views are held out (every n-th; 0 for none)."""

    fix_k3: bool = False
    fix_tangential: bool = False
    min_corners: int = 6
    min_views: int = 5
    holdout_every: int = 5
    outlier_sigma: float = 4.0
    #: a camera losing more than this fraction of its corners, in views shifted as a
    #: whole, moved (:mod:`cellcal.calib.photogrammetry.verdict`)
    max_rejected_fraction: float = 0.1
    #: the held-out board lengths' largest RMS error for a calibration that passes, mm
    max_length_rms_mm: float = 0.05
    #: measure the corners again from their edges with each camera's first calibration
    refine_corners: bool = True


def intrinsics(
    name: str,
    size: tuple[int, int],
    dets: list[tuple[int, CornerDetection]],
    pts: Array,
    options: RigCalibrationOptions,
) -> tuple[Array, Array, float, dict[int, Array]]:
    flags = (cv2.CALIB_FIX_K3 if options.fix_k3 else 0) | (
        cv2.CALIB_ZERO_TANGENT_DIST if options.fix_tangential else 0
    )
    obj = [pts[d.ids].astype(np.float32) for _, d in dets]
    img = [d.pixels.astype(np.float32).reshape(-1, 1, 2) for _, d in dets]
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    except cv2.error as exc:
        raise MeasurementError(f"{name}: calibrateCamera failed ({exc.err})") from None
    poses = {v: pose(r, t) for (v, _), r, t in zip(dets, rvecs, tvecs, strict=True)}
    return np.asarray(K, float), np.asarray(dist, float).ravel()[:5], float(rms), poses


def unseen_views(
    board: Board,
    views: Sequence[Mapping[str, Image]],
    det: list[dict[str, CornerDetection]],
    names: list[str],
    min_corners: int,
) -> list[str]:
    """One warning per view in which no camera found the board; it says so when the
    board shows mirrored there (turned over: seen through from its back)."""
    out = []
    detector = cv2.aruco.CharucoDetector(board.cv_board())
    for v, view in enumerate(views):
        if det[v] or not view:
            continue
        flipped = [n for n, im in view.items() if shows_mirrored(board, im, min_corners, detector)]
        if flipped:
            out.append(
                f"view {names[v]}: the board shows mirrored ({', '.join(flipped)}) — turned "
                "over, seen through from its back? The view is left out"
            )
        else:
            out.append(f"view {names[v]}: no camera found the board; the view is left out")
    return out


def check_inputs(
    cameras: Mapping[str, tuple[int, int]], views: Sequence[Mapping[str, Image]], names: list[str]
) -> None:
    if not cameras:
        raise InputError("cameras: at least one camera is needed")
    for v, view in enumerate(views):
        for cam, img in view.items():
            if cam not in cameras:
                raise InputError(f"view {names[v]}: {cam!r} is not one of the rig's cameras")
            w, h = cameras[cam]
            if np.shape(img)[:2] != (h, w):
                raise InputError(
                    f"view {names[v]}: {cam} image is {np.shape(img)[1]}×{np.shape(img)[0]}, "
                    f"the camera's {w}×{h}"
                )


def enough_views(
    board: Board,
    n: str,
    views: Sequence[Mapping[str, Image]],
    det: list[dict[str, CornerDetection]],
    fit: list[int],
    opt: RigCalibrationOptions,
) -> list[tuple[int, CornerDetection]]:
    """Camera ``n``'s detections in the fitted views; refused when fewer than
    ``min_views`` (naming mirrored images when that is why)."""
    dets = [(v, det[v][n]) for v in fit if n in det[v]]
    if len(dets) < opt.min_views:
        missed = [views[v][n] for v in fit if n in views[v] and n not in det[v]]
        hint = (
            " — its images show the board mirrored: is ReverseX or ReverseY set on it?"
            if mirrored_count(board, missed, opt.min_corners)
            else ""
        )
        raise MeasurementError(
            f"{n}: the board was found in {len(dets)} of the fitted views, "
            f"at least {opt.min_views} are needed{hint}"
        )
    return dets


def remeasure(
    board: Board,
    cameras: Mapping[str, tuple[int, int]],
    views: Sequence[Mapping[str, Image]],
    det: list[dict[str, CornerDetection]],
    fit: list[int],
    pts: Array,
    opt: RigCalibrationOptions,
) -> tuple[dict[str, int], list[str]]:
    """Every camera's corners measured again from their edges, with the intrinsics its
    first-pass corners give (:class:`~cellcal.calib.photogrammetry.board_corners.CornerMeter`);
    ``det`` is updated in place. A camera whose edges can be measured in fewer than
    ``min_views`` fitted views keeps the detector's corners, with a warning: a camera
    is never refused because its board's white margins are too narrow to read. Returns
    per camera the corners left out as unmeasurable, and the warnings."""
    out, warnings = {}, []
    for n in cameras:
        dets = [(v, det[v][n]) for v in fit if n in det[v]]
        K, dist, _, _ = intrinsics(n, cameras[n], dets, pts, opt)
        meter = CornerMeter(board, K, dist, opt.min_corners)
        found = {
            v: meter.measure(view[n], det[v][n]) for v, view in enumerate(views) if n in det[v]
        }
        measured = sum(1 for v in fit if found.get(v) is not None)
        if measured < opt.min_views:
            warnings.append(
                f"{n}: the board's edges could be measured in {measured} of its {len(dets)} "
                "fitted views (white margins too narrow in its images, or the board too "
                "oblique): its corners are the detector's, several times less accurate"
            )
            out[n] = 0
            continue
        for v, d in found.items():
            if d is None:
                del det[v][n]
            else:
                det[v][n] = d
        out[n] = meter.unmeasured
    return out, warnings
