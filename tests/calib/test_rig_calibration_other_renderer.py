"""Rig calibration on images cellcal's own renderer did not make.

The views come from :mod:`cellcal.mocks.rig.texture_render`, written apart from the camera
twin's renderer: a bitmap texture sampled on a regular 5×5 grid per pixel, a defocus
disk convolved with a Gaussian, other grey levels; through :func:`oblique_rig`'s four
cameras (f 1150–1350 px, principal points 15–45 px off centre, barrel distortion k1
−0.07…−0.11) and a 10×7 board of 40 mm squares (5×5 markers) seen at up to 65°. The
calibration must hold on them: no camera refused, the held-out board lengths within
0.02 mm RMS, the cameras within their reported uncertainty of the truth."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.calib.photogrammetry.camera_rig import Rig
from cellcal.calib.photogrammetry.rig_calibration import (
    RigCalibration,
    RigCalibrationOptions,
    calibrate_rig,
)
from cellcal.mocks.rig.camera_render import Image
from cellcal.mocks.rig.texture_render import RenderParams, render_board
from cellcal.mocks.rig.texture_scenes import TEST_BOARD, board_views, oblique_rig
from tests.calib.detections import kept_detections

pytestmark = pytest.mark.slow

N_VIEWS = 20

Scene = tuple[Rig, list[dict[str, Image]], RigCalibration]


@pytest.fixture(scope="module", autouse=True)
def _detections() -> Iterator[object]:
    """Each image detected once however many calibrations take it (tests/calib/detections.py)."""
    yield from kept_detections()


@pytest.fixture(scope="module")
def calibrated() -> Scene:
    rig = oblique_rig(1)
    params = RenderParams()
    views = [
        render_board(rig, TEST_BOARD, T, params, seed=100 + k)
        for k, T in enumerate(board_views(rig, TEST_BOARD, N_VIEWS, seed=1))
    ]
    cal = calibrate_rig(TEST_BOARD, _sizes(rig), views, RigCalibrationOptions(fix_k3=True))
    return rig, views, cal


def _sizes(rig: Rig) -> dict[str, tuple[int, int]]:
    return {c.name: (c.width, c.height) for c in rig.cameras}


def test_a_distorted_oblique_rig_calibrates(calibrated: Scene) -> None:
    """Barrel distortion and views to 65°: no camera refused or suspect, the held-out
    lengths within 0.02 mm RMS (0.0124 mm when written), the verdict passes."""
    _, _, cal = calibrated
    assert cal.failures == () and cal.suspect_cameras == ()
    hold = cal.holdout
    assert hold is not None and hold.lengths > 3000
    assert hold.length_rms_mm <= 0.02, hold
    assert hold.length_max_mm <= 0.2, hold
    assert hold.reprojection_rms_px <= 0.03 and cal.rms_px <= 0.03
    for rep in cal.cameras:
        assert rep.rejected <= 0.03 * rep.corners, rep.name
        assert rep.views >= 10


def test_the_cameras_are_where_the_truth_is(calibrated: Scene) -> None:
    """Intrinsics and poses against the renderer's true rig: within 4σ of what the
    calibration reports, and within 0.5 px, 0.5 mm, 0.02°."""
    rig, _, cal = calibrated
    for truth, cam, rep in zip(rig.cameras, cal.rig.cameras, cal.cameras, strict=True):
        dK = (cam.K - truth.K)[[0, 1, 0, 1], [0, 1, 2, 2]]
        sK = np.array([rep.sigma_fx_px, rep.sigma_fy_px, rep.sigma_cx_px, rep.sigma_cy_px])
        assert (np.abs(dK) <= np.maximum(4 * sK, 0.05)).all() and np.abs(dK).max() < 0.5
        assert abs(cam.dist[0] - truth.dist[0]) < 0.005
        dp = cam.T_rig_cam[:3, 3] - truth.T_rig_cam[:3, 3]
        assert np.linalg.norm(dp) < 0.5
        dR = truth.T_rig_cam[:3, :3].T @ cam.T_rig_cam[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert angle < 0.02


def test_edge_corners_beat_opencvs_on_these_images(calibrated: Scene) -> None:
    """The same views through OpenCV's corners alone (no edge measurement): the held-out
    lengths are worse, which is why the corners are measured from their edges."""
    rig, views, cal = calibrated
    opts = RigCalibrationOptions(fix_k3=True, refine_corners=False)
    plain = calibrate_rig(TEST_BOARD, _sizes(rig), views, opts)
    assert plain.holdout is not None and cal.holdout is not None
    assert plain.holdout.length_rms_mm > 1.5 * cal.holdout.length_rms_mm
