"""Calibrate a multi-camera rig from views of a ChArUco board: every camera's intrinsics
and its pose in the rig frame (the first camera's frame), with their uncertainty.

1. ChArUco corners per image (OpenCV's ``CharucoDetector``); detections with fewer than
   ``min_corners`` corners, or with all corners on one line, are dropped.
2. Per camera, ``cv2.calibrateCamera`` on its views; with those intrinsics each image's
   corners are measured again from the board's edges (:mod:`cellcal.calib.photogrammetry.views`,
   :mod:`cellcal.calib.photogrammetry.board_edges`), and ``cv2.calibrateCamera`` gives the starting
   values and the board's pose in each of the camera's views.
3. Cameras are placed one by one from views they share with cameras already placed
   (the medoid of the composed board poses); each view's board pose likewise.
4. A bundle adjustment of all of it together (:mod:`cellcal.calib.photogrammetry.bundle`), corners
   beyond ``outlier_sigma``·σ̂ dropped; what the dropped corners say — a camera that
   moved, a mismatched view, noise — by :mod:`cellcal.calib.photogrammetry.verdict`.
5. Held-out views (every ``holdout_every``-th, not used in the fit): the reprojection
   error with only the board's pose re-estimated, and the board's inner-corner distances
   triangulated from all cameras against their known lengths (mm), with a verdict.

Pure numerics: images (numpy arrays) in, a frozen :class:`RigCalibration` out. Lengths
mm, angles degrees at the boundary; ``T_a_b`` maps frame b into frame a.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry import bundle as rig_bundle
from cellcal.calib.photogrammetry.board_corners import (
    CornerDetection,
    board_not_found,
    board_points,
    detect_corners,
    grey8,
)
from cellcal.calib.photogrammetry.bundle import (
    ScaleBar,
    ScaleCheck,
    medoid,
    place_cameras,
    pose,
    scale_check,
    triangulate,
)
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Rig
from cellcal.calib.photogrammetry.verdict import CameraDiagnosis, diagnose_camera, holdout_failures
from cellcal.calib.photogrammetry.views import (
    RigCalibrationOptions,
    check_inputs,
    enough_views,
    intrinsics,
    remeasure,
    unseen_views,
)
from cellcal.calib.rotations import nearest_rotation

__all__ = [
    "CameraReport",
    "CornerDetection",
    "HoldoutCheck",
    "RigCalibration",
    "RigCalibrationOptions",
    "ScaleBar",
    "ScaleCheck",
    "board_length_errors",
    "calibrate_rig",
    "detect_corners",
    "grey8",
    "scale_check",
    "triangulate",
]
from cellcal.errors import InputError, MeasurementError

Image = NDArray[Any]


@dataclass(frozen=True, eq=False)
class CameraReport:
    """One camera's fit: views and corners used, corners rejected as outliers, the
    reprojection RMS (px) of the kept corners and of all of them, calibrateCamera's RMS
    alone, and the 1σ uncertainty of fx, fy, cx, cy (px), of the position (mm, rig frame)
    and the rotation (deg, about the camera's own axes); ``covariance`` (15, 15): fx fy
    cx cy k1 k2 p1 p2 k3 (px), rotation (rad), position (mm). The reference camera's pose
    defines the rig frame: its pose uncertainty is zero."""

    name: str
    views: int
    corners: int
    rejected: int
    rms_px: float
    rms_all_px: float
    initial_rms_px: float
    sigma_fx_px: float
    sigma_fy_px: float
    sigma_cx_px: float
    sigma_cy_px: float
    sigma_position_mm: Array
    sigma_rotation_deg: Array
    covariance: Array
    #: corners the detector found whose edges could not be measured (left out)
    unmeasured: int = 0


@dataclass(frozen=True, eq=False)
class HoldoutCheck:
    """Views left out of the fit: reprojection RMS (px) with the cameras fixed and only the
    board's pose fitted, and the board's inner-corner distances triangulated from all
    cameras that saw both corners, against the known lengths (mm)."""

    views: tuple[str, ...]
    corners: int
    reprojection_rms_px: float
    lengths: int
    length_rms_mm: float
    length_max_mm: float


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """The calibrated rig (each camera's ``reprojection_rms_px`` set), the per-camera
    fit, the overall reprojection RMS and σ̂ (px per axis), views fitted and held out,
    the held-out check, the optional scale check, cameras whose residuals say they moved,
    one-line warnings, the board poses ``T_rig_board`` of the fitted views, the solver's
    iterations, each camera's diagnosis of its rejected corners, and ``failures``: the
    causes, with their numbers, for which the result is not to be trusted (a moved
    camera, a held-out check that fails); empty when it passed."""

    rig: Rig
    cameras: tuple[CameraReport, ...]
    rms_px: float
    sigma_px: float
    fit_views: tuple[str, ...]
    holdout: HoldoutCheck | None
    scale: ScaleCheck | None
    suspect_cameras: tuple[str, ...]
    warnings: tuple[str, ...]
    T_rig_board: tuple[Array, ...]
    iterations: int
    diagnoses: tuple[CameraDiagnosis, ...] = ()
    failures: tuple[str, ...] = ()


# --- the calibration -------------------------------------------------------------------


def _observations(
    det: list[dict[str, CornerDetection]], views: list[int], names: list[str], pts: Array
) -> rig_bundle.Observations:
    cam, view, P, px = [], [], [], []
    for k, v in enumerate(views):
        for c, n in enumerate(names):
            d = det[v].get(n)
            if d is not None:
                cam.append(np.full(len(d.ids), c))
                view.append(np.full(len(d.ids), k))
                P.append(pts[d.ids])
                px.append(d.pixels)
    return rig_bundle.Observations(
        np.concatenate(cam).astype(np.int64),
        np.concatenate(view).astype(np.int64),
        np.concatenate(P),
        np.concatenate(px),
    )


def calibrate_rig(
    board: Board,
    cameras: Mapping[str, tuple[int, int]],
    views: Sequence[Mapping[str, Image]],
    options: RigCalibrationOptions | None = None,
    view_names: Sequence[str] | None = None,
    scale_bar: ScaleBar | None = None,
    name: str = "rig",
) -> RigCalibration:
    """Calibrate the rig's ``cameras`` (name → (width, height); the first is the rig
    frame) from ``views`` (one dict camera → grey image per board pose)."""
    opt = options or RigCalibrationOptions()
    names = list(cameras)
    vnames = list(view_names) if view_names is not None else [f"{k + 1}" for k in range(len(views))]
    if len(vnames) != len(views):
        raise InputError(f"view_names: {len(vnames)} names for {len(views)} views")
    check_inputs(cameras, views, vnames)
    detector = cv2.aruco.CharucoDetector(board.cv_board())
    det: list[dict[str, CornerDetection]] = []
    for view in views:
        found = {
            c: detect_corners(board, img, opt.min_corners, detector) for c, img in view.items()
        }
        det.append({c: d for c, d in found.items() if d is not None})
    if not any(det):
        raise board_not_found(board, [img for v in views for img in v.values()], opt.min_corners)
    unseen = unseen_views(board, views, det, vnames, opt.min_corners)
    every = opt.holdout_every
    held = [v for v in range(len(views)) if every > 0 and v % every == every - 1 and det[v]]
    fit = [v for v in range(len(views)) if v not in held and det[v]]
    pts = board_points(board)
    for n in names:
        enough_views(board, n, views, det, fit, opt)
    unmeasured: dict[str, int] = dict.fromkeys(names, 0)
    kept: list[str] = []
    if opt.refine_corners:
        unmeasured, kept = remeasure(board, cameras, views, det, fit, pts, opt)
        held = [v for v in held if det[v]]
        fit = [v for v in fit if det[v]]
    K0, d0, rms0, T_cam_board = {}, {}, {}, {}
    for n in names:
        dets = enough_views(board, n, views, det, fit, opt)
        K0[n], d0[n], rms0[n], poses = intrinsics(n, cameras[n], dets, pts, opt)
        T_cam_board.update({(v, n): T for v, T in poses.items()})
    T_rig_cam = place_cameras(names, T_cam_board)
    T_rig_board = [
        medoid([T_rig_cam[c] @ T_cam_board[(v, n)] for c, n in enumerate(names) if n in det[v]])
        for v in fit
    ]
    state = rig_bundle.RigState(
        np.array([[K0[n][0, 0], K0[n][1, 1], K0[n][0, 2], K0[n][1, 2], *d0[n]] for n in names]),
        np.array([T[:3, :3] for T in T_rig_cam]),
        np.array([T[:3, 3] for T in T_rig_cam]),
        np.array([T[:3, :3] for T in T_rig_board]),
        np.array([T[:3, 3] for T in T_rig_board]),
    )
    free = np.ones(9, dtype=bool)
    free[8] = not opt.fix_k3
    free[6:8] = not opt.fix_tangential
    obs = _observations(det, fit, names, pts)
    res = rig_bundle.adjust(state, obs, free, outlier_sigma=opt.outlier_sigma)
    rig, reports = _results(name, names, cameras, res, obs, fit, det, rms0, unmeasured)
    holdout = (
        _holdout(board, rig, det, held, [vnames[v] for v in held], free, opt) if held else None
    )
    fit_names = [vnames[v] for v in fit]
    diagnoses = tuple(
        diagnose_camera(n, c, res, obs, fit_names, opt.max_rejected_fraction)
        for c, n in enumerate(names)
    )
    warnings = list(unseen) + kept + [d.note for d in diagnoses if d.note is not None]
    suspects = [d.name for d in diagnoses if d.moved]
    failures = [d.note for d in diagnoses if d.moved and d.note is not None]
    inl = res.residuals[res.inliers]
    rms_px = float(np.sqrt(np.mean(np.sum(inl**2, axis=1))))
    if holdout is not None:
        failures += holdout_failures(
            holdout.reprojection_rms_px,
            rms_px,
            holdout.length_rms_mm,
            holdout.length_max_mm,
            opt.max_length_rms_mm,
        )
    st = res.state
    return RigCalibration(
        rig=rig,
        cameras=reports,
        rms_px=rms_px,
        sigma_px=res.sigma_px,
        fit_views=tuple(vnames[v] for v in fit),
        holdout=holdout,
        scale=scale_check(rig, scale_bar) if scale_bar is not None else None,
        suspect_cameras=tuple(suspects),
        warnings=tuple(warnings),
        T_rig_board=tuple(_T(R, t) for R, t in zip(st.R_rig_board, st.t_rig_board, strict=True)),
        iterations=res.iterations,
        diagnoses=diagnoses,
        failures=tuple(failures),
    )


def _T(R: Array, t: Array) -> Array:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rms(res: Array) -> float:
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(res) else float("nan")


def _results(
    rig_name: str,
    names: list[str],
    sizes: Mapping[str, tuple[int, int]],
    res: rig_bundle.BundleResult,
    obs: rig_bundle.Observations,
    fit: list[int],
    det: list[dict[str, CornerDetection]],
    rms0: dict[str, float],
    unmeasured: dict[str, int],
) -> tuple[Rig, tuple[CameraReport, ...]]:
    st = res.state
    cams, reports = [], []
    for c, n in enumerate(names):
        sel = obs.camera == c
        rms = _rms(res.residuals[sel & res.inliers])
        fx, fy, cx, cy, *dist = st.intrinsics[c]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        T = _T(st.R_rig_cam[c], st.p_rig_cam[c])
        if c == 0:
            T = np.eye(4)
        else:  # re-orthonormalise what the updates left
            T[:3, :3] = nearest_rotation(T[:3, :3])
        w, h = sizes[n]
        cams.append(Camera(n, w, h, K, np.array(dist), T, rms))
        sd = np.sqrt(np.clip(np.diag(res.camera_cov[c]), 0.0, None))
        reports.append(
            CameraReport(
                name=n,
                views=sum(1 for v in fit if n in det[v]),
                corners=int((sel & res.inliers).sum()),
                rejected=int((sel & ~res.inliers).sum()),
                rms_px=rms,
                rms_all_px=_rms(res.residuals[sel]),
                initial_rms_px=rms0[n],
                sigma_fx_px=float(sd[0]),
                sigma_fy_px=float(sd[1]),
                sigma_cx_px=float(sd[2]),
                sigma_cy_px=float(sd[3]),
                sigma_position_mm=sd[12:15].copy(),
                sigma_rotation_deg=np.degrees(sd[9:12]),
                covariance=res.camera_cov[c].copy(),
                unmeasured=unmeasured[n],
            )
        )
    return Rig(rig_name, tuple(cams)), tuple(reports)


def _holdout(
    board: Board,
    rig: Rig,
    det: list[dict[str, CornerDetection]],
    held: list[int],
    held_names: list[str],
    free: NDArray[np.bool_],
    opt: RigCalibrationOptions,
) -> HoldoutCheck:
    """Reprojection and length errors on the held-out views, cameras fixed."""
    names = [c.name for c in rig.cameras]
    pts = board_points(board)
    boards = []
    for v in held:
        n = max(det[v], key=lambda k: len(det[v][k].ids))
        cam, d = rig.camera(n), det[v][n]
        ok, rvec, tvec = cv2.solvePnP(pts[d.ids], d.pixels, cam.K, cam.dist)
        if not ok:
            raise MeasurementError(f"{n}: the board's pose in a held-out view is not found")
        boards.append(cam.T_rig_cam @ pose(rvec, tvec))
    state = rig_bundle.RigState(
        np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *c.dist[:5]] for c in rig.cameras]),
        np.array([c.T_rig_cam[:3, :3] for c in rig.cameras]),
        np.array([c.T_rig_cam[:3, 3] for c in rig.cameras]),
        np.array([T[:3, :3] for T in boards]),
        np.array([T[:3, 3] for T in boards]),
    )
    obs = _observations(det, held, names, pts)
    res = rig_bundle.adjust(state, obs, free, fix_cameras=True, outlier_sigma=opt.outlier_sigma)
    err = board_length_errors(board, rig, [det[v] for v in held])
    return HoldoutCheck(
        views=tuple(held_names),
        corners=int(res.inliers.sum()),
        reprojection_rms_px=_rms(res.residuals[res.inliers]),
        lengths=len(err),
        length_rms_mm=float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        length_max_mm=float(np.abs(err).max()) if len(err) else float("nan"),
    )


def board_length_errors(
    board: Board, rig: Rig, views: Sequence[Mapping[str, CornerDetection]]
) -> Array:
    """Measured minus known distance (mm) between every two of a view's board corners,
    each triangulated from every camera of ``rig`` that saw it (VDI/VDE 2634-1 style),
    for each view's detections (camera name → corners)."""
    pts = board_points(board)
    errors = [np.zeros(0)]
    for det in views:
        seen: dict[int, list[tuple[Camera, Array]]] = {}
        for n, d in det.items():
            for i, px in zip(d.ids, d.pixels, strict=True):
                seen.setdefault(int(i), []).append((rig.camera(n), px))
        ids = sorted(i for i, s in seen.items() if len(s) >= 2)
        X = np.array([triangulate(*zip(*seen[i], strict=True)) for i in ids]).reshape(-1, 3)
        iu, ju = np.triu_indices(len(ids), k=1)
        measured = np.linalg.norm(X[iu] - X[ju], axis=1)
        known = np.linalg.norm(pts[ids][iu] - pts[ids][ju], axis=1)
        errors.append(measured - known)
    out: Array = np.concatenate(errors)
    return out
