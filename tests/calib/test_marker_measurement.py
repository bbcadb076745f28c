"""Marker corners to a few hundredths of a pixel, and the target's pose from all cameras
at once with an uncertainty that matches its error. Images are rendered by the camera
twin at known poses; OpenCV's own corner refinement is measured beside ours."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cellcal.calib.photogrammetry.camera_rig import Camera, Marker, Rig, Target
from cellcal.calib.photogrammetry.marker_corners import MarkerFinder, Window, grey_levels
from cellcal.calib.photogrammetry.marker_lines import marker_corners
from cellcal.calib.photogrammetry.target_pose import measure_target
from cellcal.errors import InputError, MeasurementError
from cellcal.mocks.rig.camera_render import Optics, SceneRenderer
from cellcal.mocks.rig.scene import dome_target, four_camera_rig, volume_centre
from tests.lazy import Rotation

K = [[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]]
DIST = [-0.2, 0.1, 0.001, -0.001, 0.0]
FACING = np.diag([1.0, -1.0, -1.0])


def _marker_scene(dist: list[float]) -> tuple[Camera, Marker, SceneRenderer]:
    cam = Camera("cam0", 1280, 1024, K, dist, np.eye(4))
    marker = Marker(7, 40.0, np.eye(4))
    target = Target("t", "DICT_4X4_50", [0, 0, 0], (marker,))
    return cam, marker, SceneRenderer.for_target((cam,), target, Optics())


def _poses(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(25)).as_matrix()
        T[:3, :3] = T[:3, :3] @ FACING
        T[:3, 3] = [rng.uniform(-300, 300), rng.uniform(-250, 250), 1250.0]
        out.append(T)
    return out


@pytest.mark.parametrize("dist", [[0.0] * 5, DIST], ids=["pinhole", "distorted"])
def test_edge_fitted_corners_beat_opencv_subpix_tenfold(dist: list[float]) -> None:
    """Blur 0.8 px and noise 2 grey levels: our corners within 0.04 px RMS and unbiased;
    OpenCV's CORNER_REFINE_SUBPIX on the same images ten times worse."""
    cam, marker, renderer = _marker_scene(dist)
    finder = MarkerFinder("DICT_4X4_50")
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    opencv = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params
    )
    rng = np.random.default_rng(7)
    ours, theirs = [], []
    for T in _poses(rng, 12):
        img = renderer.frames(renderer.clean(T), rng)["cam0"]
        truth = cam.project(marker.corners() @ T[:3, :3].T + T[:3, 3])
        found = marker_corners(cam, finder.find(img))
        assert [m.id for m in found] == [7]
        px = cam.project(np.c_[found[0].xy, np.ones(4)])
        ours.append(px - truth)
        corners, _ids, _ = opencv.detectMarkers(img)
        theirs.append(corners[0].reshape(4, 2) - truth)
    e, o = np.concatenate(ours), np.concatenate(theirs)
    rms, rms_cv = float(np.sqrt((e**2).mean())), float(np.sqrt((o**2).mean()))
    assert rms < 0.04
    assert np.abs(e.mean(axis=0)).max() < 0.01
    assert rms_cv > 10 * rms


def test_image_kinds_and_windows() -> None:
    cam, _marker, renderer = _marker_scene([0.0] * 5)
    T = np.eye(4)
    T[:3, :3] = FACING
    T[:3, 3] = [30.0, -20.0, 1250.0]
    img = renderer.frames(renderer.clean(T), np.random.default_rng(1))["cam0"]
    finder = MarkerFinder("DICT_4X4_50")
    ref = marker_corners(cam, finder.find(img))[0].xy
    # 16-bit and colour images give the same corners
    for other in (img.astype(np.uint16) * 257, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)):
        got = marker_corners(cam, finder.find(other))[0].xy
        assert np.abs(got - ref).max() * 1000 < 0.01
    # a window around the marker finds it, one elsewhere does not
    c = cam.project(T[:3, 3][None])[0]
    near = Window(int(c[0]) - 40, int(c[1]) - 40, int(c[0]) + 40, int(c[1]) + 40)
    assert [m.id for m in finder.find(img, near)] == [7]
    assert finder.find(img, Window(0, 0, 200, 200)) == []
    # ids outside the target's are ignored; a blank image has no markers
    assert MarkerFinder("DICT_4X4_50", frozenset({3})).find(img) == []
    assert finder.find(np.zeros((1024, 1280), np.uint8)) == []
    with pytest.raises(InputError, match="pixel type"):
        grey_levels(img.astype(np.float32))
    with pytest.raises(InputError, match="not a grey or colour image"):
        grey_levels(np.zeros((10, 10, 2), np.uint8))


def test_a_marker_cut_by_the_image_border_is_not_measured() -> None:
    """Half a marker is not a marker: the detector may find what is left, but corners
    from edges that leave the image would be biased, so nothing is returned."""
    cam, _, renderer = _marker_scene([0.0] * 5)
    T = np.eye(4)
    T[:3, :3] = FACING
    # the marker's centre projects 6 px inside the right border: its right edge is out
    T[:3, 3] = [(1279 - 6 - 639.5) * 1.25, 0.0, 1250.0]
    img = renderer.frames(renderer.clean(T), np.random.default_rng(2))["cam0"]
    assert marker_corners(cam, MarkerFinder("DICT_4X4_50").find(img)) == []


def _cube_scene() -> tuple[Rig, Target, SceneRenderer, np.ndarray]:
    rig, target = four_camera_rig(), dome_target()
    renderer = SceneRenderer.for_target(rig.cameras, target, Optics())
    return rig, target, renderer, volume_centre(rig)


def _views(rig: Rig, target: Target, images: dict[str, np.ndarray]) -> dict:
    finder = MarkerFinder(target.dictionary, frozenset(m.id for m in target.markers))
    return {c.name: marker_corners(c, finder.find(images[c.name])) for c in rig.cameras}


def _facing_pose(rng: np.random.Generator, centre: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    tilt = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(20))
    T[:3, :3] = (tilt * Rotation.from_euler("x", 180, degrees=True)).as_matrix()
    T[:3, 3] = centre + rng.uniform(-120, 120, 3)
    return T


def test_the_pose_from_four_cameras_and_its_covariance() -> None:
    """Per frame the reference point lands within tens of micrometres, and the predicted
    covariance matches the observed error (mean squared Mahalanobis distance per
    coordinate near 1)."""
    rig, target, renderer, centre = _cube_scene()
    rng = np.random.default_rng(11)
    errors, m2 = [], []
    for _ in range(16):
        T = _facing_pose(rng, centre)
        views = _views(rig, target, renderer.frames(renderer.clean(T), rng))
        pose = measure_target(rig, target, views)
        e = pose.xyz_mm - T[:3, 3]
        errors.append(e)
        m2.append(float(e @ np.linalg.solve(pose.cov_mm2, e)) / 3)
        assert len(pose.cameras) >= 2 and pose.markers >= 2
        assert np.allclose(pose.cov_mm2, pose.cov_mm2.T)
        assert np.all(np.linalg.eigvalsh(pose.cov_pose) > 0)
        assert pose.reprojection_rms_px < 0.1
        dR = pose.T_rig_target[:3, :3] @ T[:3, :3].T
        assert np.degrees(np.linalg.norm(Rotation.from_matrix(dR).as_rotvec())) < 0.05
    rms = float(np.sqrt((np.array(errors) ** 2).sum(axis=1).mean()))
    assert rms < 0.06
    assert 0.4 < float(np.mean(m2)) < 2.0


def test_fewer_than_two_cameras_is_a_clear_refusal() -> None:
    rig, target, renderer, centre = _cube_scene()
    T = _facing_pose(np.random.default_rng(3), centre)
    views = _views(rig, target, renderer.frames(renderer.clean(T), np.random.default_rng(4)))
    only = {"cam2": views["cam2"], "cam0": [], "cam1": [], "cam3": []}
    with pytest.raises(MeasurementError, match=r"seen by 1 camera\(s\) \(cam2\); at least 2"):
        measure_target(rig, target, only)
    with pytest.raises(MeasurementError, match=r"seen by 0 camera\(s\) \(none\)"):
        measure_target(rig, target, {})


def test_a_moved_camera_is_dropped_and_named() -> None:
    """One camera knocked 2 mm and 0.2° after calibration: its view no longer fits the
    others; it is left out, named, and the result stays right."""
    rig, target, renderer, centre = _cube_scene()
    T = _facing_pose(np.random.default_rng(5), centre)
    views = _views(rig, target, renderer.frames(renderer.clean(T), np.random.default_rng(6)))
    bumped = np.eye(4)
    bumped[:3, :3] = Rotation.from_euler("y", 0.2, degrees=True).as_matrix()
    bumped[:3, 3] = [2.0, 0.0, 0.0]
    cams = list(rig.cameras)
    c = cams[3]
    cams[3] = Camera(c.name, c.width, c.height, c.K, c.dist, c.T_rig_cam @ bumped)
    pose = measure_target(Rig(rig.name, tuple(cams)), target, views)
    assert pose.cameras == ("cam0", "cam1", "cam2")
    assert any(d.startswith("cam3: view RMS") for d in pose.dropped)
    assert np.linalg.norm(pose.xyz_mm - T[:3, 3]) < 0.1


def test_a_series_is_followed_and_averaged() -> None:
    """20 frames of a still target: the mean is within 0.03 mm, the markers are followed
    after the first frame, and the covariance of the mean is far below a frame's."""
    from cellcal.calib.photogrammetry.rig_measurement import TargetMeter

    rig, target, renderer, centre = _cube_scene()
    rng = np.random.default_rng(21)
    T = _facing_pose(rng, centre)
    clean = renderer.clean(T)
    sets = [renderer.frames(clean, rng) for _ in range(20)]
    meter = TargetMeter(rig, target)
    calls = {"find": 0}
    original = meter._finder._detect

    def counting(*args: object, **kwargs: object) -> list:
        calls["find"] += 1
        return original(*args, **kwargs)  # type: ignore[arg-type]

    meter._finder._detect = counting  # type: ignore[method-assign]
    mean, poses = meter.series(sets)
    assert mean.n == 20 and not mean.failures
    assert np.linalg.norm(mean.xyz_mm - T[:3, 3]) < 0.03
    assert calls["find"] == len(rig.cameras)  # the detector ran on the first frame only
    frame_var = np.trace(poses[0].cov_mm2)
    assert np.trace(mean.cov_mm2) < frame_var / 3
    assert np.trace(mean.scatter_cov_mm2) > 0
    assert np.allclose(mean.T_rig_target[:3, :3] @ mean.T_rig_target[:3, :3].T, np.eye(3))


def test_a_target_that_moves_is_found_again() -> None:
    """The meter follows a still target; when it moves 40 mm between frames, the
    followed markers are not where expected and the detector finds them again."""
    from cellcal.calib.photogrammetry.rig_measurement import TargetMeter

    rig, target, renderer, centre = _cube_scene()
    rng = np.random.default_rng(22)
    T1 = _facing_pose(rng, centre)
    T2 = T1.copy()
    T2[:3, 3] += [40.0, -25.0, 10.0]
    meter = TargetMeter(rig, target)
    meter.measure(renderer.frames(renderer.clean(T1), rng))
    pose = meter.measure(renderer.frames(renderer.clean(T2), rng))
    assert np.linalg.norm(pose.xyz_mm - T2[:3, 3]) < 0.1
    with pytest.raises(InputError, match="not in rig"):
        meter.measure({"cam9": np.zeros((10, 10), np.uint8)})


def test_a_camera_that_sees_no_marker_is_searched_once_per_still_target() -> None:
    """A camera the target is hidden from is searched whole on the first frame and not
    again while the others follow a still target; a new series, or a target that moved,
    has it searched again."""
    from cellcal.calib.photogrammetry.rig_measurement import TargetMeter

    rig, target, renderer, centre = _cube_scene()
    rng = np.random.default_rng(23)
    T = _facing_pose(rng, centre)
    clean = renderer.clean(T)
    hidden = rig.cameras[3].name
    blank = np.full((1024, 1280), 40, np.uint8)

    def frames() -> dict[str, np.ndarray]:
        return {**renderer.frames(clean, rng), hidden: blank}

    meter = TargetMeter(rig, target)
    searched: list[int] = []
    original = meter._finder._detect

    def counting(image: np.ndarray, window: object = None) -> list:
        if image is blank:
            searched.append(1)
        return original(image, window)  # type: ignore[arg-type]

    meter._finder._detect = counting  # type: ignore[method-assign]
    mean, poses = meter.series([frames() for _ in range(6)])
    assert mean.n == 6 and all(hidden not in p.cameras for p in poses)
    assert len(searched) == 1
    meter.series([frames() for _ in range(3)])  # a new series looks again, once
    assert len(searched) == 2
    moved = T.copy()
    moved[:3, 3] += [40.0, -25.0, 10.0]
    meter.measure({**renderer.frames(renderer.clean(moved), rng), hidden: blank})
    meter.measure({**renderer.frames(renderer.clean(moved), rng), hidden: blank})
    assert len(searched) == 3  # the target moved: searched again (then not)


def test_a_batch_of_sets_follows_the_target_while_it_stays() -> None:
    """`rig measure --sets` (``measure_next``): sets of one pose are followed from the
    set before (the detector runs on the first set only) and each keeps its own numbers,
    within a frame's noise of a fresh search; a set of another pose is measured afresh,
    to the same numbers as a meter that never saw the sets before."""
    from cellcal.calib.photogrammetry.rig_measurement import TargetMeter

    rig, target, renderer, centre = _cube_scene()
    rng = np.random.default_rng(23)
    T1 = _facing_pose(rng, centre)
    T2 = T1.copy()
    T2[:3, 3] += [60.0, -30.0, 20.0]
    first = [renderer.frames(renderer.clean(T1), rng) for _ in range(4)]
    second = renderer.frames(renderer.clean(T2), rng)
    meter = TargetMeter(rig, target)
    calls = {"find": 0}
    original = meter._finder._detect

    def counting(*args: object, **kwargs: object) -> list:
        calls["find"] += 1
        return original(*args, **kwargs)  # type: ignore[arg-type]

    meter._finder._detect = counting  # type: ignore[method-assign]
    followed = [meter.measure_next(s) for s in first]
    assert calls["find"] == len(rig.cameras)  # the first set only
    for s, pose in zip(first, followed, strict=True):
        fresh = TargetMeter(rig, target).measure(s)
        assert np.linalg.norm(pose.xyz_mm - fresh.xyz_mm) < 3 * np.sqrt(np.trace(fresh.cov_mm2))
        assert np.linalg.norm(pose.xyz_mm - T1[:3, 3]) < 0.1
    moved = meter.measure_next(second)
    alone = TargetMeter(rig, target).measure(second)
    np.testing.assert_array_equal(moved.xyz_mm, alone.xyz_mm)
    assert np.linalg.norm(moved.xyz_mm - T2[:3, 3]) < 0.1
