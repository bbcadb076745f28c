"""The renderer the camera twin draws with: its own bias must be far below the
detector's (pixel centres at integer coordinates, area-exact edges, symmetric blur)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Target
from cellcal.mocks.rig.camera_render import Optics, SceneRenderer, exposed
from cellcal.mocks.rig.scene import dome_target, four_camera_rig, volume_centre

K = [[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]]


def _one_marker(optics: Optics, x_mm: float) -> tuple[np.ndarray, np.ndarray]:
    cam = Camera("cam0", 1280, 1024, K, [0.0] * 5, np.eye(4))
    marker = Marker(7, 40.0, np.eye(4))
    target = Target("t", "DICT_4X4_50", [0, 0, 0], (marker,))
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # facing the camera
    T[:3, 3] = [x_mm, 0.0, 1250.0]
    img = SceneRenderer.for_target((cam,), target, optics).clean(T)["cam0"]
    truth = cam.project(marker.corners() @ T[:3, :3].T + T[:3, 3])
    return img, truth


@pytest.mark.parametrize("x_mm", [0.0, 0.3, 0.625, 0.9])
@pytest.mark.parametrize("blur", [0.0, 0.8])
def test_an_edge_splits_its_row_where_the_projection_says(x_mm: float, blur: float) -> None:
    """Along a row through the marker's left edge the grey levels' sum puts the edge at
    the projected corner's u, to a hundredth of a pixel: pixels integrate area around
    integer centres, and the blur is symmetric."""
    o = Optics(blur_px=blur, noise_grey=0.0)
    img, truth = _one_marker(o, x_mm)
    u_edge = truth[0, 0]  # left edge (top-left corner's u)
    row = img[511].astype(np.float64)
    i0 = round(u_edge) - 3  # 7 pixels: inside the 5.3 px black border
    window = row[i0 : i0 + 7]
    # white plate left of the edge, black border right of it
    u = (window.sum() + o.white * (i0 - 0.5) - o.black * (i0 + 6.5)) / (o.white - o.black)
    assert u == pytest.approx(u_edge, abs=0.01)


def test_faces_turned_away_are_not_drawn() -> None:
    rig = four_camera_rig()
    target = dome_target()
    T = np.eye(4)
    T[:3, 3] = volume_centre(rig)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # the +z face looks at the cameras
    clean = SceneRenderer.for_target(rig.cameras, target, Optics(blur_px=0.0)).clean(T)
    img = clean["cam0"]
    # only the +z face and the side faces cameras see: the image is not empty...
    assert img.max() == pytest.approx(Optics().white, abs=1e-3)
    # ... and a flipped cube shows its open (flange) side: no marker faces the rig
    T[:3, :3] = np.eye(3)
    flipped = SceneRenderer.for_target(rig.cameras, target, Optics(blur_px=0.0)).clean(T)
    n_white = {k: int((v > 200).sum()) for k, v in flipped.items()}
    n_front = {k: int((v > 200).sum()) for k, v in clean.items()}
    assert all(n_white[k] < n_front[k] for k in n_front)


def test_noise_is_fresh_per_frame_and_has_the_asked_level() -> None:
    clean = np.full((200, 300), 100.0, dtype=np.float32)
    rng = np.random.default_rng(0)
    a = exposed(clean, rng, 2.0).astype(np.float64)
    b = exposed(clean, rng, 2.0).astype(np.float64)
    assert a.dtype == np.float64 and not np.array_equal(a, b)
    assert np.std(a) == pytest.approx(np.sqrt(4.0 + 1.0 / 12.0), rel=0.05)
    assert np.mean(a) == pytest.approx(100.0, abs=0.05)
    # saturates instead of wrapping
    hot = exposed(np.full((10, 10), 254.5, dtype=np.float32), rng, 5.0)
    assert hot.dtype == np.uint8 and hot.min() > 240


@pytest.mark.parametrize(
    ("dist", "rotvec"),
    [([0.0] * 5, [0.0, 0.0, 0.0]), ([-0.12, 0.05, 0.0005, -0.0004, 0.0], [0.3, -0.2, 0.1])],
)
def test_a_board_renders_its_chessboard_and_markers(dist, rotvec) -> None:
    """The rendered ChArUco board is found by OpenCV's own board detector, every inner
    chessboard corner, within 0.1 px of where the board's geometry projects it: facing
    the camera, and tilted through a lens with distortion."""
    import cv2
    from scipy.spatial.transform import Rotation

    board = Board("DICT_4X4_50", (7, 5), 40.0, 30.0)
    cam = Camera("cam0", 1280, 1024, K, dist, np.eye(4))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = [-140.0, -100.0, 900.0]
    img = SceneRenderer.for_board((cam,), board, Optics(noise_grey=0.0)).clean(T)["cam0"]
    img8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(img8)
    assert ids is not None and len(ids) == 6 * 4
    obj = board.cv_board().getChessboardCorners()[ids.ravel()]
    truth = cam.project(obj @ T[:3, :3].T + T[:3, 3])
    assert np.abs(corners.reshape(-1, 2) - truth).max() < 0.1


def _tilted_poses(n: int, seed: int):
    from scipy.spatial.transform import Rotation

    rig = four_camera_rig()
    rng = np.random.default_rng(seed)
    for _ in range(n):
        T = np.eye(4)
        tilt = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(30))
        T[:3, :3] = (tilt * Rotation.from_euler("x", 180, degrees=True)).as_matrix()
        T[:3, 3] = volume_centre(rig) + rng.uniform(-150, 150, 3)
        yield T


@pytest.mark.parametrize("dist", [[0.0] * 5, [-0.12, 0.05, 0.0005, -0.0004, 0.0]])
def test_sampling_only_where_the_scene_changes_gives_the_fully_sampled_image(dist) -> None:
    """The adaptive renderer against sampling every pixel, on tilted targets (among them
    a pose where two faces leave a sliver of background thinner than a pixel between
    them, which check points at the pixels' corners alone miss by 70 grey levels): it
    differs only in the few pixels a bit's corner pokes into between the probes, by
    under a tenth of the black-white step, before the blur."""
    rig = four_camera_rig()
    cameras = tuple(Camera(c.name, c.width, c.height, c.K, dist, c.T_rig_cam) for c in rig.cameras)
    sharp = Optics(blur_px=0.0, noise_grey=0.0)  # each pixel as it was sampled
    fast = SceneRenderer.for_target(cameras, dome_target(), sharp)
    full = SceneRenderer.for_target(cameras, dome_target(), replace(sharp, adaptive=False))
    worst, counts = [], []
    for T in _tilted_poses(6, seed=3):
        a, b = fast.clean(T), full.clean(T)
        for name in a:
            d = np.abs(a[name] - b[name])
            worst.append(float(d.max()))
            counts.append(int((d > 1e-3).sum()))
            assert b[name].max() > 200  # the camera saw the target
    assert max(worst) < 25.0 and max(counts) <= 20, (worst, counts)


def test_a_region_is_the_image_less_its_plain_background() -> None:
    from cellcal.mocks.rig.camera_render import render, render_region

    rig = four_camera_rig()
    target = SceneRenderer.for_target(rig.cameras, dome_target(), Optics())
    T = next(_tilted_poses(1, seed=5))
    cam = rig.cameras[0]
    whole = render(cam, target.faces, T, Optics())
    part, (rows, cols) = render_region(cam, target.faces, T, Optics())
    assert part.shape == whole[rows, cols].shape and part.size < whole.size / 10
    np.testing.assert_array_equal(whole[rows, cols], part)
    outside = np.ones(whole.shape, bool)
    outside[rows, cols] = False
    assert (whole[outside] == Optics().background).all()
    away = np.eye(4)
    away[:3, 3] = [0.0, 0.0, -5000.0]  # behind every camera
    empty, _ = render_region(cam, target.faces, away, Optics())
    assert empty.size == 0
