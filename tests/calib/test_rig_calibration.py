"""Rig calibration from ChArUco views rendered by the camera twin: the four-camera rig's
intrinsics and poses against the truth, the reported 1σ against the actual errors, the
held-out checks, a camera that moved during the capture, and the refusals.

The views are rendered once per module at supersample 3 (corner errors 0.05 px per
axis, unbiased; the renderer's default supersample 8 costs several times more), and each
image is detected once (tests/calib/detections.py)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from cellcal.calib.geometry import Array, invert
from cellcal.calib.photogrammetry import bundle as rig_bundle
from cellcal.calib.photogrammetry.board_corners import CornerDetection, CornerMeter
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Rig
from cellcal.calib.photogrammetry.rig_calibration import (
    RigCalibration,
    RigCalibrationOptions,
    ScaleBar,
    calibrate_rig,
    detect_corners,
    grey8,
    scale_check,
    triangulate,
)
from cellcal.calib.photogrammetry.rig_measurement import TargetMeter
from cellcal.errors import (
    DegenerateGeometryError,
    FileFormatError,
    InputError,
    MeasurementError,
)
from cellcal.files.images import load_views, read_image
from cellcal.mocks.rig.camera_render import Image, Optics, SceneRenderer, board_face
from cellcal.mocks.rig.scene import board_poses, dome_target, four_camera_rig, volume_centre
from tests.calib.detections import kept_detections
from tests.lazy import Rotation

pytestmark = pytest.mark.slow

BOARD = Board("DICT_4X4_50", (7, 5), 60.0, 45.0)
OPTICS = Optics(supersample=3, blur_px=0.8, noise_grey=2.0)
N_VIEWS = 20

Scene = tuple[Rig, list[Array], list[dict[str, Image]]]


@pytest.fixture(scope="module", autouse=True)
def _detections() -> Iterator[object]:
    """Each image detected once however many calibrations take it (tests/calib/detections.py)."""
    yield from kept_detections()


def _sizes(rig: Rig) -> dict[str, tuple[int, int]]:
    return {c.name: (c.width, c.height) for c in rig.cameras}


@pytest.fixture(scope="module")
def scene() -> Scene:
    rig = four_camera_rig()
    poses = board_poses(rig, BOARD, N_VIEWS, seed=11)
    renderer = SceneRenderer.for_board(rig.cameras, BOARD, OPTICS)
    rng = np.random.default_rng(5)
    views = [renderer.frames(renderer.clean(T), rng) for T in poses]
    return rig, poses, views


def _scale_bar(rig: Rig, views: list[dict[str, Image]]) -> tuple[ScaleBar, float]:
    """The board's first and last inner corners in the last (held-out) view, seen by every
    camera, as a scale bar of known length."""
    dets = {n: detect_corners(BOARD, img) for n, img in views[-1].items()}
    pts = np.asarray(BOARD.cv_board().getChessboardCorners(), dtype=np.float64)
    a, b = 0, len(pts) - 1
    pa, pb = {}, {}
    for n, d in dets.items():
        if d is not None and a in d.ids and b in d.ids:
            pa[n] = d.pixels[list(d.ids).index(a)]
            pb[n] = d.pixels[list(d.ids).index(b)]
    length = float(np.linalg.norm(pts[b] - pts[a]))
    return ScaleBar(pa, pb, length), length


@pytest.fixture(scope="module")
def calibrated(scene: Scene) -> RigCalibration:
    rig, _, views = scene
    bar, _ = _scale_bar(rig, views)
    options = RigCalibrationOptions(fix_k3=True, fix_tangential=True, holdout_every=5)
    return calibrate_rig(BOARD, _sizes(rig), views, options, scale_bar=bar, name="cell-rig")


def _errors(truth: Camera, cam: Camera) -> tuple[Array, Array, Array]:
    """Errors of (fx, fy, cx, cy) px, the position (mm, rig frame) and the rotation (deg,
    about the camera's own axes)."""
    dK = (cam.K - truth.K)[[0, 1, 0, 1], [0, 1, 2, 2]]
    dp = cam.T_rig_cam[:3, 3] - truth.T_rig_cam[:3, 3]
    dR = truth.T_rig_cam[:3, :3].T @ cam.T_rig_cam[:3, :3]
    return dK, dp, np.degrees(Rotation.from_matrix(dR).as_rotvec())


def test_rig_matches_the_truth(scene: Scene, calibrated: RigCalibration) -> None:
    """Intrinsics within 1 px, positions within 1 mm and rotations within 0.05° of the
    truth (cam0 = identity, as the truth's rig frame); reprojection RMS < 0.15 px."""
    rig, _, _ = scene
    res = calibrated
    assert res.rig.name == "cell-rig"
    assert [c.name for c in res.rig.cameras] == ["cam0", "cam1", "cam2", "cam3"]
    np.testing.assert_array_equal(res.rig.cameras[0].T_rig_cam, np.eye(4))
    assert res.fit_views == ("1", "2", "3", "4", "6", "7", "8", "9", "11", "12", "13", "14",
                             "16", "17", "18", "19")  # fmt: skip
    for truth, cam, rep in zip(rig.cameras, res.rig.cameras, res.cameras, strict=True):
        dK, dp, dr = _errors(truth, cam)
        assert np.abs(dK).max() < 1.0, (cam.name, dK)
        assert np.abs(dp).max() < 1.0, (cam.name, dp)
        assert np.abs(dr).max() < 0.05, (cam.name, dr)
        np.testing.assert_array_equal(cam.dist[2:], 0.0)  # tangential and k3 held at zero
        assert abs(cam.dist[0]) < 0.01
        assert cam.reprojection_rms_px == rep.rms_px < 0.15
        # a view whose corners' edges cannot be measured is left out (15 or 16 views)
        assert rep.views >= 15 and rep.corners > 300 and rep.rejected < 0.08 * rep.corners
        assert rep.initial_rms_px < 0.5
    assert res.rms_px < 0.15 and 0.005 < res.sigma_px < 0.08
    assert res.suspect_cameras == () and res.warnings == ()
    assert len(res.T_rig_board) == 16


def test_held_out_views_and_scale(scene: Scene, calibrated: RigCalibration) -> None:
    """Held-out views: reprojection RMS like the fit's; the board's inner-corner
    distances triangulated to 0.3 mm RMS; a 350 mm scale bar to 0.1 %."""
    hold = calibrated.holdout
    assert hold is not None
    assert hold.views == ("5", "10", "15", "20")
    assert hold.corners > 300 and hold.reprojection_rms_px < 0.15
    assert hold.lengths > 1000 and hold.length_rms_mm < 0.3 and hold.length_max_mm < 1.5
    scale = calibrated.scale
    assert scale is not None
    assert abs(scale.ratio - 1.0) < 1e-3 and scale.known_mm == pytest.approx(np.hypot(300, 180))


def test_reported_sigma_matches_the_errors(scene: Scene, calibrated: RigCalibration) -> None:
    """Actual error over reported 1σ: RMS between 1/3 and 3 for the intrinsics, the
    positions and the rotations; none beyond 5σ."""
    rig, _, _ = scene
    z = []
    for truth, cam, rep in zip(
        rig.cameras, calibrated.rig.cameras, calibrated.cameras, strict=True
    ):
        dK, dp, dr = _errors(truth, cam)
        sK = np.array([rep.sigma_fx_px, rep.sigma_fy_px, rep.sigma_cx_px, rep.sigma_cy_px])
        assert (sK > 0.02).all() and (sK < 1.0).all()
        z += list(dK / sK)
        if cam.name == "cam0":
            np.testing.assert_array_equal(rep.sigma_position_mm, 0.0)
            continue
        assert (rep.sigma_position_mm < 1.0).all() and (rep.sigma_rotation_deg < 0.05).all()
        z += list(dp / rep.sigma_position_mm) + list(dr / rep.sigma_rotation_deg)
    zz = np.array(z)
    assert 1 / 3 < np.sqrt(np.mean(zz**2)) < 3.0, zz
    assert np.abs(zz).max() < 5.0, zz


def test_moved_camera_is_flagged(scene: Scene) -> None:
    """cam2 knocked by 0.3° and 2 mm after the first 6 views: its corners of those views
    are rejected and it is named; the other cameras are not."""
    rig, poses, views = scene
    cams = list(rig.cameras)
    knock = np.eye(4)
    knock[:3, :3] = Rotation.from_euler("y", 0.3, degrees=True).as_matrix()
    knock[:3, 3] = [2.0, 0.0, 0.0]
    c2 = cams[2]
    moved = Camera(c2.name, c2.width, c2.height, c2.K, c2.dist, c2.T_rig_cam @ knock)
    renderer = SceneRenderer.for_board((moved,), BOARD, OPTICS)
    rng = np.random.default_rng(9)
    mixed = [dict(v) for v in views]
    for k in range(6):
        mixed[k].update(renderer.frames(renderer.clean(poses[k]), rng))
    res = calibrate_rig(BOARD, _sizes(rig), mixed)  # all five distortion terms free
    assert res.suspect_cameras == ("cam2",)
    assert len(res.warnings) == 1 and res.warnings[0].startswith("cam2: views 1, 2, 3, 4, 6")
    assert res.failures[0] == res.warnings[0] and "the camera moved" in res.failures[0]
    rep = {r.name: r for r in res.cameras}
    assert rep["cam2"].rms_all_px > 1.0 and rep["cam2"].rejected > 0.2 * rep["cam2"].corners
    assert all(rep[n].rms_all_px < 0.3 for n in ("cam0", "cam1", "cam3"))


def test_too_few_views_is_refused(scene: Scene) -> None:
    rig, _, views = scene
    few = [{k: v for k, v in view.items() if k != "cam3" or i < 4} for i, view in enumerate(views)]
    with pytest.raises(MeasurementError, match=r"^cam3: the board was found in 4 of the fitted"):
        calibrate_rig(BOARD, _sizes(rig), few)


def test_camera_sharing_no_view_is_refused(scene: Scene) -> None:
    rig, _, views = scene
    split = [
        {k: v for k, v in view.items() if (k == "cam3") == (i >= 10)}
        for i, view in enumerate(views)
    ]
    with pytest.raises(DegenerateGeometryError, match=r"^cam3: never sees the board in a view"):
        calibrate_rig(BOARD, _sizes(rig), split, RigCalibrationOptions(holdout_every=0))


def test_mirrored_images_are_refused(scene: Scene) -> None:
    rig, _, views = scene
    flipped = [{k: np.ascontiguousarray(v[:, ::-1]) for k, v in view.items()} for view in views[:3]]
    with pytest.raises(MeasurementError) as err:
        calibrate_rig(BOARD, _sizes(rig), flipped)
    assert str(err.value) == (
        "board found only in mirrored images — is ReverseX or ReverseY set on the cameras, "
        "or is the board seen through from its back?"
    )


def test_a_camera_giving_mirrored_images_is_named(scene: Scene) -> None:
    """cam1 with ReverseX set: its images show no board; the refusal names it and why."""
    rig, _, views = scene
    mixed = [{**v, "cam1": np.ascontiguousarray(v["cam1"][:, ::-1])} for v in views]
    with pytest.raises(
        MeasurementError,
        match=r"^cam1: the board was found in 0 of the fitted views, at least 5 are needed — "
        r"its images show the board mirrored: is ReverseX or ReverseY set on it\?$",
    ):
        calibrate_rig(BOARD, _sizes(rig), mixed)


def test_a_board_turned_over_is_flagged_and_left_out(
    scene: Scene, calibrated: RigCalibration
) -> None:
    """Views 2 and 7 taken with the board turned over (a glass board seen through from its
    back: the pattern mirrored) and view 12 with the board outside every camera: each
    left out with a warning naming it; the rig is the same as without those views."""
    rig, poses, views = scene
    half = np.eye(4)
    half[:3, 3] = [BOARD.squares[0] * BOARD.square / 2, BOARD.squares[1] * BOARD.square / 2, 0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("y", 180, degrees=True).as_matrix()
    glass = replace(board_face(BOARD), front=1.0)  # the pattern seen through the glass
    behind = SceneRenderer(rig.cameras, (glass,), OPTICS)
    rng = np.random.default_rng(3)
    mixed = list(views)
    for k in (1, 6):
        over = poses[k] @ half @ turn @ invert(half)
        mixed[k] = behind.frames(behind.clean(over), rng)
    renderer = SceneRenderer.for_board(rig.cameras, BOARD, OPTICS)
    away = poses[11].copy()
    away[:3, 3] += [3000.0, 0.0, 0.0]
    mixed[11] = renderer.frames(renderer.clean(away), rng)
    bar, _ = _scale_bar(rig, views)
    options = RigCalibrationOptions(fix_k3=True, fix_tangential=True, holdout_every=5)
    res = calibrate_rig(BOARD, _sizes(rig), mixed, options, scale_bar=bar)
    assert res.warnings[:2] == (
        "view 2: the board shows mirrored (cam0, cam1, cam2, cam3) — turned over, seen "
        "through from its back? The view is left out",
        "view 7: the board shows mirrored (cam0, cam1, cam2, cam3) — turned over, seen "
        "through from its back? The view is left out",
    )
    assert res.warnings[2:] == ("view 12: no camera found the board; the view is left out",)
    assert res.suspect_cameras == ()
    assert "2" not in res.fit_views and "7" not in res.fit_views and "12" not in res.fit_views
    assert len(res.fit_views) == 13
    for a, b in zip(res.rig.cameras, calibrated.rig.cameras, strict=True):
        assert np.abs(a.K - b.K).max() < 1.0
        assert np.abs(a.T_rig_cam[:3, 3] - b.T_rig_cam[:3, 3]).max() < 1.0


def test_wrong_legacy_flag_is_named() -> None:
    """A 7×6 board (even rows: the pre-4.6 pattern differs) described with legacy = true:
    markers are found, corners are not; the refusal says which pattern the images show."""
    rig = four_camera_rig()
    board = Board("DICT_4X4_50", (7, 6), 50.0, 37.0)
    T = np.eye(4)
    T[:3, 3] = volume_centre(rig) - [175.0, 150.0, 0.0]
    cams = rig.cameras[:1]
    renderer = SceneRenderer.for_board(cams, board, Optics(supersample=1))
    views = [renderer.frames(renderer.clean(T), np.random.default_rng(0))]
    assert detect_corners(board, views[0]["cam0"]) is not None
    legacy = Board("DICT_4X4_50", (7, 6), 50.0, 37.0, legacy=True)
    with pytest.raises(MeasurementError, match=r"legacy = false\)$") as err:
        calibrate_rig(legacy, _sizes(Rig("r", cams)), views)
    assert str(err.value).startswith("board not found in any view — is `legacy` right?")


def test_input_checks(scene: Scene) -> None:
    rig, _, views = scene
    with pytest.raises(InputError, match=r"^view 1: 'cam9' is not one of the rig's cameras"):
        calibrate_rig(BOARD, _sizes(rig), [{"cam9": views[0]["cam0"]}])
    small = {"cam0": views[0]["cam0"][:512]}
    with pytest.raises(InputError, match=r"^view a: cam0 image is 1280×512, the camera's"):
        calibrate_rig(BOARD, _sizes(rig), [small], view_names=["a"])


def test_grey8_and_16_bit_detection(scene: Scene) -> None:
    _, _, views = scene
    img = views[0]["cam1"]
    wide = img.astype(np.uint16) * 257
    np.testing.assert_array_equal(grey8(wide), np.clip(np.rint(wide * (255 / wide.max())), 0, 255))
    colour = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    a, b = detect_corners(BOARD, img), detect_corners(BOARD, colour)
    assert a is not None and b is not None
    np.testing.assert_allclose(a.pixels, b.pixels)
    c = detect_corners(BOARD, wide)
    assert c is not None and len(c.ids) == len(a.ids)


def test_bundle_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(0)
    C, V, m = 3, 4, 40
    intr = np.tile([1000, 1010, 640, 512, -0.2, 0.1, 0.001, -0.002, 0.03], (C, 1)).astype(float)
    Rc = Rotation.from_rotvec(rng.normal(0, 0.2, (C, 3))).as_matrix()
    pc = rng.normal(0, 100, (C, 3))
    Rb = Rotation.from_rotvec(rng.normal(0, 0.3, (V, 3))).as_matrix()
    tb = rng.normal(0, 50, (V, 3)) + np.array([0.0, 0.0, 1200.0])
    P = np.c_[rng.uniform(0, 300, (m, 2)), np.zeros(m)]
    obs = rig_bundle.Observations(rng.integers(0, C, m), rng.integers(0, V, m), P, np.zeros((m, 2)))
    state = rig_bundle.RigState(intr, Rc, pc, Rb, tb)
    uv, J_in, J_cam, J_board = rig_bundle.project(state, obs)
    h = 1e-6

    def moved(**kw: Array) -> Array:
        s = rig_bundle.RigState(**{**state.__dict__, **kw})
        return (rig_bundle.project(s, obs)[0] - uv) / h

    def turn(R: Array, k: int) -> Array:
        out: Array = R @ Rotation.from_rotvec(h * np.eye(3)[k]).as_matrix()
        return out

    for k in range(9):
        d = intr.copy()
        d[:, k] += h
        np.testing.assert_allclose(moved(intrinsics=d), J_in[:, :, k], rtol=1e-5, atol=1e-4)
    for k in range(3):
        np.testing.assert_allclose(moved(R_rig_cam=turn(Rc, k)), J_cam[:, :, k], atol=1e-3)
        np.testing.assert_allclose(
            moved(p_rig_cam=pc + h * np.eye(3)[k]), J_cam[:, :, 3 + k], atol=1e-5
        )
        np.testing.assert_allclose(moved(R_rig_board=turn(Rb, k)), J_board[:, :, k], atol=1e-3)
        np.testing.assert_allclose(
            moved(t_rig_board=tb + h * np.eye(3)[k]), J_board[:, :, 3 + k], atol=1e-5
        )


def test_triangulation_is_exact_on_exact_pixels() -> None:
    rig = four_camera_rig(dist=(-0.1, 0.05, 0.001, 0.0, 0.0))
    X = volume_centre(rig) + np.array([30.0, -40.0, 25.0])
    pixels = [c.project(X[None])[0] for c in rig.cameras]
    np.testing.assert_allclose(triangulate(rig.cameras, pixels), X, atol=1e-6)
    bar = ScaleBar(
        {c.name: p for c, p in zip(rig.cameras, pixels, strict=True)},
        {c.name: c.project((X + np.array([100.0, 0.0, 0.0]))[None])[0] for c in rig.cameras[:2]},
        100.0,
    )
    assert scale_check(rig, bar).ratio == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(MeasurementError, match="at least two cameras"):
        triangulate(rig.cameras[:1], pixels[:1])
    assert invert(rig.cameras[0].T_rig_cam)[3, 3] == 1.0


def _png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    path.write_bytes(buf.tobytes())


def test_load_views(tmp_path: Path) -> None:
    grey = np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) % 251
    _png(tmp_path / "v10" / "cam0.png", grey.astype(np.uint8))
    _png(tmp_path / "v2" / "cam0.png", (grey * 200).astype(np.uint16))
    _png(tmp_path / "v2" / "cam10.png", cv2.cvtColor(grey.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    _png(tmp_path / "v2" / "cam2.png", grey.astype(np.uint8))
    (tmp_path / "v2" / "notes.txt").write_text("ignored")
    (tmp_path / ".hidden").mkdir()
    vs = load_views(tmp_path)
    assert vs.names == ("v2", "v10")
    assert list(vs.cameras) == ["cam0", "cam2", "cam10"] and vs.cameras["cam0"] == (64, 48)
    assert vs.views[0]["cam0"].dtype == np.uint16 and vs.views[1]["cam0"].dtype == np.uint8
    np.testing.assert_array_equal(vs.views[0]["cam10"], grey)
    assert set(vs.views[1]) == {"cam0"}


def test_unreadable_images_are_named(tmp_path: Path) -> None:
    grey = (np.arange(48 * 64).reshape(48, 64) % 251).astype(np.uint8)
    _png(tmp_path / "a" / "cam0.png", grey)
    bad = tmp_path / "a" / "cam1.png"
    data = (tmp_path / "a" / "cam0.png").read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match=r"cam1\.png: not a complete image") as err:
        load_views(tmp_path)
    assert "\n" not in str(err.value)
    bad.write_bytes(b"\x89PNG garbage" + data[-12:])
    with pytest.raises(FileFormatError, match=r"cam1\.png: not a complete image"):
        read_image(bad)
    bad.unlink()
    _png(tmp_path / "b" / "cam0.png", grey[:40])
    with pytest.raises(FileFormatError, match=r"b/cam0\.png: 64×40 px, but .*a/cam0\.png"):
        load_views(tmp_path)
    (tmp_path / "b" / "cam0.png").unlink()
    with pytest.raises(FileFormatError, match=r"b: no <camera>\.png images in this folder"):
        load_views(tmp_path)
    with pytest.raises(FileFormatError, match="not a directory"):
        load_views(tmp_path / "missing")


def test_a_calibrated_rig_measures_lengths(scene: Scene, calibrated: RigCalibration) -> None:
    """The flange's target at 10 poses (5 frames each) measured with the calibrated rig:
    the distances between its reference points (up to about 350 mm) within 0.025 mm RMS of the
    truth (VDI/VDE 2634-1 style; benchmarks/photogrammetry.py does 24 poses × 20)."""
    rig, _, _ = scene
    target = dome_target()
    renderer = SceneRenderer.for_target(rig.cameras, target, Optics(blur_px=0.8, noise_grey=2.0))
    meter = TargetMeter(calibrated.rig, target)
    rng = np.random.default_rng(17)
    measured, truth = [], []
    for _ in range(10):
        T = np.eye(4)
        tilt = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(15))
        T[:3, :3] = (tilt * Rotation.from_euler("x", 180, degrees=True)).as_matrix()
        T[:3, 3] = volume_centre(rig) + rng.uniform(-150, 150, 3)
        clean = renderer.clean(T)
        mean, _ = meter.series([renderer.frames(clean, rng) for _ in range(5)])
        measured.append(mean.xyz_mm)
        truth.append(T[:3, 3] + T[:3, :3] @ target.reference)
    iu, ju = np.triu_indices(10, k=1)
    P, Q = np.array(measured), np.array(truth)
    known = np.linalg.norm(Q[iu] - Q[ju], axis=1)
    err = np.linalg.norm(P[iu] - P[ju], axis=1) - known
    assert known.min() > 20.0 and known.max() > 250.0
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms < 0.025, (rms, np.abs(err).max())


def _bundle_with(residuals: Array, inliers: Array, views: Array) -> tuple:
    obs = rig_bundle.Observations(
        np.zeros(len(views), dtype=np.int64), views.astype(np.int64),
        np.zeros((len(views), 3)), np.zeros((len(views), 2)),
    )  # fmt: skip
    state = rig_bundle.RigState(*(np.zeros((1, 1)),) * 5)
    res = rig_bundle.BundleResult(state, inliers, residuals, 0.05, np.zeros((1, 15, 15)), 1)
    return res, obs


def test_a_moved_camera_is_told_from_noisy_detections() -> None:
    """The rule of rig_verdict: 12 views of 30 corners with 0.05 px noise. Outliers
    scattered over every view (15 %) are noisy detections: named, the camera kept. The
    last four views shifted as a whole by 0.8 px: the camera moved, and the note names
    those views and the shift. One shifted view alone is a mismatched view."""
    from cellcal.calib.photogrammetry.verdict import diagnose_camera

    rng = np.random.default_rng(3)
    views = np.repeat(np.arange(12), 30)
    names = [f"v{k}" for k in range(12)]
    noise = rng.normal(0.0, 0.05, (len(views), 2))
    scattered = rng.random(len(views)) < 0.15
    noisy = noise + np.where(scattered[:, None], rng.normal(0.0, 1.0, (len(views), 2)), 0.0)
    d = diagnose_camera("cam2", 0, *_bundle_with(noisy, ~scattered, views), names, 0.1)
    assert not d.moved and d.shifted == () and d.rejected == scattered.sum()
    assert d.note is not None and "noisy detections" in d.note and "did not move" in d.note
    shift = noise + np.where((views >= 8)[:, None], [0.8, 0.0], 0.0)
    d = diagnose_camera("cam2", 0, *_bundle_with(shift, views < 8, views), names, 0.1)
    assert d.moved and d.shifted == ("v8", "v9", "v10", "v11")
    assert d.note is not None and d.note.startswith("cam2: views v8, v9, v10, v11 are shifted")
    assert "by 0.80–0.81 px" in d.note and "the camera moved" in d.note
    one = noise + np.where((views == 5)[:, None], [0.0, 0.9], 0.0)
    d = diagnose_camera("cam2", 0, *_bundle_with(one, views != 5, views), names, 0.05)
    assert not d.moved and d.shifted == ("v5",) and "view v5 is shifted" in (d.note or "")
    clean = diagnose_camera("cam2", 0, *_bundle_with(noise, views >= 0, views), names, 0.1)
    assert clean.note is None and not clean.moved


def test_a_camera_whose_edges_cannot_be_read_keeps_the_detectors_corners(
    scene: Scene, monkeypatch: pytest.MonkeyPatch
) -> None:
    """When a camera's board edges cannot be measured (white margins too narrow in its
    images), it is not refused: it keeps OpenCV's corners, and a warning says so."""
    from cellcal.calib.photogrammetry import views as rig_views

    made: list[CornerMeter] = []

    class Meter(CornerMeter):  # the cameras are measured in order: the 4th is cam3's
        def __init__(self, *args: object, **kw: object) -> None:
            super().__init__(*args, **kw)  # type: ignore[arg-type]
            made.append(self)

        def measure(self, image: Image, first: CornerDetection | None = None) -> object:
            return None if len(made) == 4 else super().measure(image, first)

    monkeypatch.setattr(rig_views, "CornerMeter", Meter)
    rig, _, views = scene
    res = calibrate_rig(BOARD, _sizes(rig), views, RigCalibrationOptions(fix_k3=True))
    assert res.warnings[0].startswith("cam3: the board's edges could be measured in 0 of its")
    rep = {r.name: r for r in res.cameras}
    assert rep["cam3"].views == 16 and rep["cam3"].unmeasured == 0
    assert rep["cam0"].unmeasured > 0


def test_the_second_measurement_of_a_view_starts_from_its_first_markers(scene: Scene) -> None:
    """CornerMeter given a view's first detection takes its markers as they are: the
    same corners, to the bit, as finding the markers again."""
    rig, _, views = scene
    cam = rig.cameras[0]
    meter = CornerMeter(BOARD, cam.K, cam.dist)
    compared = 0
    for view in views[:4]:
        image = view[cam.name]
        first = detect_corners(BOARD, image)
        if first is None:
            continue
        assert first.markers is not None and len(first.markers[1]) > 0
        again, given = meter.measure(image), meter.measure(image, first)
        assert again is not None and given is not None
        assert np.array_equal(again.ids, given.ids)
        assert np.array_equal(again.pixels, given.pixels)
        compared += 1
    assert compared >= 2
