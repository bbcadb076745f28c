"""The independent renderer (``cellcal/mocks/rig/texture_render.py``) checked on its own terms:
OpenCV finds its boards where the camera model says, its pixel centres sit at integer
coordinates, its grey levels are what it was asked for, it is deterministic, and its
distortion inversion agrees with ``cv2.projectPoints``."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from cellcal.calib.photogrammetry.camera_rig import Camera, Rig
from cellcal.mocks.rig.texture_render import (
    Psf,
    RenderParams,
    TexturedPlane,
    board_plane,
    distort,
    pixels_to_normalised,
    psf_kernel,
    render,
    render_board,
    render_clean,
    render_target,
)
from cellcal.mocks.rig.texture_scenes import (
    TEST_BOARD,
    board_views,
    oblique_rig,
    plate_target,
    target_poses,
    volume_centre,
)

SHARP = RenderParams(psf=None, sensor=None)


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.radians([rx, ry, rz]))
    return np.asarray(R)


def _board_facing(
    cam: Camera, pixel: tuple[float, float], depth: float, R: np.ndarray
) -> np.ndarray:
    """T_rig_board with the board's centre on the ray of ``pixel`` at ``depth`` (mm), its
    orientation ``R`` in the camera frame (identity: fronto-parallel)."""
    x, y = pixels_to_normalised(cam, np.array([pixel]))[0]
    nx, ny = TEST_BOARD.squares
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = depth * np.array([x, y, 1.0]) - R[:, :2] @ (np.array([nx, ny]) * 20.0)
    out: np.ndarray = cam.T_rig_cam @ T
    return out


def test_a_board_is_found_where_the_camera_model_projects_it() -> None:
    """CharucoDetector finds every corner with the right id; refined by cornerSubPix
    they lie within 0.15 px of cv2.projectPoints of the true corners (25° tilt, off the
    image's centre where the lens distorts, default blur and noise)."""
    cam = oblique_rig(3).cameras[1]
    T = _board_facing(cam, (880.0, 660.0), 1250.0, _rot(25.0, -8.0, 17.0))
    img = render_board(oblique_rig(3), TEST_BOARD, T, RenderParams(), seed=4)[cam.name]
    cb = TEST_BOARD.cv_board()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(img)
    assert ids is not None and len(ids) == len(cb.getChessboardCorners())
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    found = cv2.cornerSubPix(img, corners.astype(np.float32), (3, 3), (-1, -1), crit)
    obj = np.asarray(cb.getChessboardCorners(), dtype=np.float64)[ids.ravel()]
    pts = obj @ T[:3, :3].T + T[:3, 3]
    T_cam_rig = np.linalg.inv(cam.T_rig_cam)
    rvec, _ = cv2.Rodrigues(T_cam_rig[:3, :3])
    truth, _ = cv2.projectPoints(pts, rvec, T_cam_rig[:3, 3], cam.K, cam.dist)
    err = found.reshape(-1, 2) - truth.reshape(-1, 2)
    assert np.abs(err).max() < 0.15
    assert np.abs(err.mean(axis=0)).max() < 0.03


def _edge_scene(u_edge: float, tilt_deg: float = 0.0) -> tuple[Camera, TexturedPlane, np.ndarray]:
    """A distortion-free camera (f = 1000 px, 200×160) and a fronto-parallel plate 1 m
    away filling it, black left of x = 70 mm and white right of it, the edge at column
    ``u_edge`` through the image's centre row, turned ``tilt_deg`` about the optical axis;
    and the edge's two ends in pixels."""
    K = np.array([[1000.0, 0.0, 100.0], [0.0, 1000.0, 80.0], [0.0, 0.0, 1.0]])
    cam = Camera("edge", 200, 160, K, np.zeros(5), np.eye(4))
    t = 0.1  # mm a texel: 0.1 px
    tex = np.full((1400, 1400), SHARP.white, np.float32)
    tex[:, :700] = SHARP.black
    A = np.array([[1 / t, 0, -0.5], [0, 1 / t, -0.5], [0, 0, 1]])
    R = _rot(0.0, 0.0, tilt_deg)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([u_edge - 100.0, 0.0, 1000.0]) - R @ [70.0, 70.0, 0.0]
    ends = (np.array([[70.0, 0.0, 0.0], [70.0, 140.0, 0.0]]) @ R.T + T[:3, 3])[:, :2] + [100, 80]
    return cam, TexturedPlane(tex, T, A, front=-1), ends


def _area_crossings(img: np.ndarray, rows: range, u0: int, u1: int) -> np.ndarray:
    """Per row, where the grey levels' sum over columns u0..u1 puts a dark-to-bright edge
    (the pixel boxes' area split: the 50 % crossing of the integrated profile)."""
    dark = (SHARP.white - img[rows.start : rows.stop, u0:u1]) / (SHARP.white - SHARP.black)
    out: np.ndarray = u0 - 0.5 + dark.sum(axis=1)
    return out


@pytest.mark.parametrize("u_edge", [100.0, 100.13, 100.37, 100.5, 100.81])
def test_an_edge_falls_where_pixel_centres_at_integers_put_it(u_edge: float) -> None:
    """Pixel u covers [u − 0.5, u + 0.5): the grey levels put a sharp edge within 0.02 px
    of its place (32×32 samples, no blur, no noise); an edge on a pixel centre makes that
    pixel 50 % grey, one on a pixel boundary splits the two pixels clean."""
    cam, plane, _ = _edge_scene(u_edge)
    img = render_clean(cam, [plane], replace(SHARP, supersample=32))
    assert np.abs(_area_crossings(img, range(70, 90), 90, 111) - u_edge).max() < 0.02
    img5 = render_clean(cam, [plane], SHARP)
    if u_edge == 100.0:
        assert img5[80, 100] == pytest.approx((SHARP.black + SHARP.white) / 2, abs=1e-3)
    if u_edge == 100.5:
        assert img5[80, 100] == pytest.approx(SHARP.black, abs=1e-3)
        assert img5[80, 101] == pytest.approx(SHARP.white, abs=1e-3)


def test_a_slanted_edge_is_unbiased_with_the_default_5x5_samples() -> None:
    """With the default regular 5×5 grid one row's crossing may be off by up to 0.1 px
    (the grid's step; 0.03 px measured, the texels' ramp smooths it), but along a slanted
    edge those errors average out: the mean offset from the true line is within 0.005 px."""
    cam, plane, ends = _edge_scene(100.3, tilt_deg=5.0)
    img = render_clean(cam, [plane], SHARP)
    rows = range(30, 130)
    (ua, va), (ub, vb) = ends
    truth = ua + (np.arange(rows.start, rows.stop) - va) * (ub - ua) / (vb - va)
    err = np.array(
        [
            _area_crossings(img, range(v, v + 1), int(u) - 8, int(u) + 9)[0] - u
            for v, u in zip(rows, truth, strict=True)
        ]
    )
    assert np.abs(err).max() < 0.06
    assert abs(err.mean()) < 0.005


def test_grey_levels_inside_squares_are_black_and_white() -> None:
    """Inside a black square the image is ``black``, in a white square's margin around its
    marker ``white``; sharp exactly, with blur and noise on average."""
    cam = oblique_rig(1).cameras[0]
    T = _board_facing(cam, (640.0, 512.0), 700.0, _rot(5.0, 0.0, 0.0))
    planes = [board_plane(TEST_BOARD, T, SHARP)]
    sharp = render_clean(cam, planes, SHARP)
    noisy = render(cam, planes, RenderParams(), np.random.default_rng(3)).astype(np.float64)
    sq, (nx, ny) = TEST_BOARD.square, TEST_BOARD.squares
    black, white = [], []
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:  # top-left black
                black.append([sq * (i + 0.5), sq * (j + 0.5)])
            else:  # the 5 mm strip between marker and square edge
                white += [[sq * i + 2.5, sq * (j + 0.5)], [sq * (i + 0.5), sq * j + 2.5]]
    for pts, level, tol in ((black, SHARP.black, 0.4), (white, SHARP.white, 1.0)):
        xyz = np.column_stack([pts, np.zeros(len(pts))]) @ T[:3, :3].T + T[:3, 3]
        px = np.round(cam.project(xyz)).astype(int)
        win = np.array(
            [[img[v - 1 : v + 2, u - 1 : u + 2] for u, v in px] for img in (sharp, noisy)]
        )
        assert np.abs(win[0] - level).max() < 1e-3
        assert abs(win[1].mean() - level) < tol


def test_same_seed_same_frames() -> None:
    rig = oblique_rig(2)
    assert all(
        np.array_equal(a.K, b.K) and np.array_equal(a.T_rig_cam, b.T_rig_cam)
        for a, b in zip(rig.cameras, oblique_rig(2).cameras, strict=True)
    )
    poses = board_views(rig, TEST_BOARD, 3, seed=5)
    again = board_views(oblique_rig(2), TEST_BOARD, 3, seed=5)
    assert all(np.array_equal(a, b) for a, b in zip(poses, again, strict=True))
    one_camera = Rig("one", rig.cameras[1:2])
    one = render_board(one_camera, TEST_BOARD, poses[0], RenderParams(), seed=9)["cam1"]
    two = render_board(one_camera, TEST_BOARD, poses[0], RenderParams(), seed=9)["cam1"]
    other = render_board(one_camera, TEST_BOARD, poses[0], RenderParams(), seed=10)["cam1"]
    assert np.array_equal(one, two) and not np.array_equal(one, other)


def test_the_nearest_plate_hides_the_others_whatever_their_order() -> None:
    """Depth test: a black plate 100 mm in front of a white one hides it where they
    overlap, in either order."""
    cam, base, _ = _edge_scene(100.0)  # a plate over u 30..170 at 1 m
    far = replace(base, texture=np.full_like(base.texture, SHARP.white))
    T = base.T_rig_plane.copy()
    T[:3, 3] += [40.0, 0.0, -100.0]  # over u 67..222 at 0.9 m
    near = replace(base, texture=np.full_like(base.texture, SHARP.black), T_rig_plane=T)
    a = render_clean(cam, [far, near], SHARP)
    assert np.array_equal(a, render_clean(cam, [near, far], SHARP))
    assert a[80, 50] == SHARP.white and a[80, 120] == SHARP.black and a[80, 190] == SHARP.black


@pytest.mark.parametrize("seed", [1, 2])
def test_the_distortion_inversion_round_trips_with_opencv(seed: int) -> None:
    """Every 8th pixel of the whole image (edges and corners too), undistorted by the
    module's Newton inversion and projected again by cv2.projectPoints, comes back within
    1e-6 px; the forward model is OpenCV's."""
    for cam in oblique_rig(seed).cameras:
        u, v = np.meshgrid(
            np.r_[np.arange(-0.5, cam.width, 8.0), cam.width - 0.5],
            np.r_[np.arange(-0.5, cam.height, 8.0), cam.height - 0.5],
        )
        px = np.column_stack([u.ravel(), v.ravel()])
        xy = pixels_to_normalised(cam, px)
        rays = np.column_stack([xy, np.ones(len(xy))])
        back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        assert np.abs(back.reshape(-1, 2) - px).max() < 1e-6
        xd, yd = distort(xy[:, 0], xy[:, 1], cam.dist)
        mine = np.column_stack([cam.K[0, 0] * xd + cam.K[0, 2], cam.K[1, 1] * yd + cam.K[1, 2]])
        assert np.abs(mine - back.reshape(-1, 2)).max() < 1e-9


def test_the_oblique_rig_is_what_it_says() -> None:
    for seed in range(6):
        rig = oblique_rig(seed)
        centre, _ = volume_centre(rig)
        assert np.array_equal(rig.cameras[0].T_rig_cam, np.eye(4))
        dirs = []
        for cam in rig.cameras:
            (fx, _, cx), (_, fy, cy), _ = cam.K
            assert 1150 <= fx <= 1350 and 1.001 <= fy / fx <= 1.003
            assert 15 <= np.hypot(cx - 639.5, cy - 511.5) <= 45
            k1, k2, p1, p2, k3 = cam.dist
            assert -0.11 <= k1 <= -0.07 and 0.02 <= k2 <= 0.08 and k3 == 0
            assert max(abs(p1), abs(p2)) <= 3e-4
            d = cam.T_rig_cam[:3, 3] - centre
            assert 1100 <= np.linalg.norm(d) <= 1400
            dirs.append(d / np.linalg.norm(d))
        cos = np.array(dirs) @ np.array(dirs).T
        angles = np.degrees(np.arccos(np.clip(cos[np.triu_indices(4, 1)], -1, 1)))
        assert angles.min() >= 35 and angles.max() <= 60


def test_board_views_are_seen_by_two_cameras_and_tilted_up_to_65_degrees() -> None:
    rig = oblique_rig(1)
    corners = np.asarray(TEST_BOARD.cv_board().getChessboardCorners(), dtype=np.float64)
    steep = 0
    for T in board_views(rig, TEST_BOARD, 12, seed=3):
        centre = T[:3, :3] @ [200.0, 140.0, 0.0] + T[:3, 3]
        seen, worst = 0, 0.0
        for cam in rig.cameras:
            to_cam = cam.T_rig_cam[:3, 3] - centre
            inc = np.degrees(np.arccos(-T[:3, 2] @ to_cam / np.linalg.norm(to_cam)))
            px = cam.project(corners @ T[:3, :3].T + T[:3, 3])
            inside = ((px >= 0) & (px < [cam.width, cam.height])).all(axis=1).mean()
            if inc < 80 and inside > 0.1:
                worst = max(worst, inc)
                seen += inside >= 0.9
        assert seen >= 2 and worst <= 65.0
        steep += worst >= 50.0
    assert steep >= 3


def test_the_target_is_found_with_its_corners_in_the_detectors_order() -> None:
    """Every camera that sees the target finds its markers by id; each detected corner is
    near the projection of the target file's corner of the same index (TL, TR, BR, BL)."""
    rig, target = oblique_rig(1), plate_target()
    T = target_poses(rig, target, 1, seed=2)[0]
    images = render_target(rig, target, T, RenderParams(), seed=1)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100)
    detector = cv2.aruco.ArucoDetector(dictionary)
    found = 0
    for cam in rig.cameras:
        corners, ids, _ = detector.detectMarkers(images[cam.name])
        for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=True):
            (m,) = [m for m in target.markers if m.id == i]
            truth = cam.project(m.corners() @ T[:3, :3].T + T[:3, 3])
            assert np.abs(c.reshape(4, 2) - truth).max() < 2.5
        found += ids is not None and len(ids) >= 4
    assert found >= 2


def test_the_blur_kernel_is_a_disk_and_a_gaussian() -> None:
    """Sums to 1, symmetric, its variance per axis r²/4 + σ² + 1/12 (disk, Gaussian,
    pixel cell)."""
    psf = Psf(0.7, 0.5)
    k = psf_kernel(psf).astype(np.float64)
    assert k.sum() == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(k, k.T, atol=1e-7) and np.allclose(k, k[::-1], atol=1e-7)
    x = np.arange(k.shape[0]) - k.shape[0] // 2
    var = float((k.sum(axis=0) * x**2).sum())
    assert var == pytest.approx(0.7**2 / 4 + 0.5**2 + 1 / 12, rel=0.02)
