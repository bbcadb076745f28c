"""Photogrammetry benchmark: cellcal's marker measurement against two OpenCV pipelines, on
the same rendered images, in one run, on two scenes rendered by two different renderers.

Scenes (20 frames per pose: one clean render per camera per pose, fresh noise per frame;
the rig is the renderer's own, perfect):

1. the bundled cell, the camera twin's renderer (``mocks/rig/camera_render.py``): 4 cameras
   1280×1024, f = 1000 px, no distortion, about 1.25 m from the volume; the flange fixture
   of five 40 mm DICT_4X4_50 markers; blur 0.8 px, noise 2 grey levels; poses anywhere in a
   300 mm cube, tilted up to 20°;
2. the other renderer (``mocks/rig/texture_render.py``, written apart from the first): its
   oblique rig (4 cameras 1280×1024, fx 1150–1350 px, principal points 15–45 px off
   centre, barrel lenses k1 −0.07…−0.11, 1.1–1.4 m away, rays 35–60° apart), defocus disk
   0.7 px with a Gaussian of 0.5 px, noise 2 grey levels, and two targets of DICT_5X5_100
   markers on tilted faces: its own ``flange-plate`` (45, 30, 30, 20, 20, 20 mm) and
   ``flange-mixed`` (60, 45, 30, 30, 20, 20 mm): 12–68 px in the images, the 20 mm ones
   too small to measure (a border under 4 px); poses tilted up to 30°.

Pipelines, each timed on the same in-memory frames (image decoding excluded):

* cellcal: ``TargetMeter.series``: the first frame located at half resolution and
  searched in the target's window, then the markers followed (edges measured where the
  last pose puts them, no detector), corners from edge lines, the pose from all cameras at
  once, the mean of the frames with its propagated covariance;
* OpenCV whole-frame: ``ArucoDetector`` with ``CORNER_REFINE_SUBPIX`` on each whole
  frame, corners undistorted (``undistortPoints``), each corner seen by two or more
  cameras triangulated (N-view linear DLT), the target's corner model fitted to them
  (Kabsch), the mean of the frames;
* OpenCV windowed (the honest peer): the same, but after the first frame the detector
  runs only in a window around the markers each camera found in the last frame, with
  cellcal's margin (``WINDOW_MARGIN_PX``), and on the whole frame when that finds none.

Printed per scene: the reference point's 3-D error of the series mean (RMS over poses)
for each pipeline and the accuracy ratios; cellcal's mean squared Mahalanobis distance
per coordinate; sets per second for each and the ratios (each series timed ``--repeat``
times, the pipelines in turn, the least kept: the machine is shared), and cellcal's rate
measuring each set on its own as ``rig measure --sets`` does (``measure_next``: no mean,
each set's own numbers, followed from the set before while the target is still there).

Then, on the bundled scene's series, the same measured with a calibrated rig instead of
the perfect one, as a cell would: a 7×5 ChArUco board (60 mm squares) rendered in 20
views through the same cameras (supersample 8, blur 0.8 px, noise 2 grey levels),
calibrated by cellcal's ``calibrate_rig`` and by OpenCV (``calibrateCamera`` per camera,
``stereoCalibrate`` of each camera against the first with the intrinsics fixed). The
length error in the manner of VDI/VDE 2634 part 1: the distance between the reference
points of every pair of poses against the true distance; RMS and largest.

Goals (issue 11 and its follow-up): series mean ≤ 0.012 mm RMS and ≥ 10× more accurate
than either OpenCV pipeline; Mahalanobis 0.6–1.6 (bundled scene); ≥ 100 four-camera sets
per second, ≥ 3× the whole-frame pipeline and ≥ 2× the windowed one; with the calibrated
rig, length error ≤ 0.02 mm RMS.
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.calib.geometry import Array, invert
from cellcal.calib.photogrammetry.board_corners import board_points
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Rig, Target
from cellcal.calib.photogrammetry.rig_calibration import (
    RigCalibrationOptions,
    calibrate_rig,
    detect_corners,
)
from cellcal.calib.photogrammetry.rig_measurement import WINDOW_MARGIN_PX, TargetMeter
from cellcal.calib.rigid_solvers import svd_rotation
from cellcal.mocks.rig import texture_render as tex
from cellcal.mocks.rig.camera_render import Image, Optics, SceneRenderer
from cellcal.mocks.rig.scene import board_poses, dome_target, four_camera_rig, volume_centre
from cellcal.mocks.rig.texture_scenes import oblique_rig, plate_target, target_poses

BOARD = Board("DICT_4X4_50", (7, 5), 60.0, 45.0)
#: cellcal measuring each set on its own, as ``rig measure --sets`` does (measure_next)
ALONE = "cellcal set by set"
Sets = list[dict[str, Image]]


def _poses(rng: np.random.Generator, centre: Array, n: int) -> list[Array]:
    out = []
    for _ in range(n):
        T = np.eye(4)
        tilt = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(20))
        T[:3, :3] = (tilt * Rotation.from_euler("x", 180, degrees=True)).as_matrix()
        T[:3, 3] = centre + rng.uniform(-150, 150, 3)
        out.append(T)
    return out


def mixed_target() -> Target:
    """Six DICT_5X5_100 markers (ids 80–85) of 60, 45, 30, 30, 20 and 20 mm on faces tilted
    0–35° from the flange axis, the reference point off every marker centre."""

    def face(x: float, y: float, z: float, tilt_deg: float, toward_deg: float) -> Array:
        a = np.radians(toward_deg)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(
            np.radians(tilt_deg) * np.array([-np.sin(a), np.cos(a), 0.0])
        ).as_matrix()
        T[:3, 3] = [x, y, z]
        return T

    sizes_faces = [
        (60.0, (0.0, 0.0, 40.0, 0.0, 0.0)),
        (45.0, (-88.0, 0.0, 30.0, 25.0, 180.0)),
        (30.0, (80.0, 6.0, 32.0, 20.0, 0.0)),
        (30.0, (4.0, -72.0, 26.0, 15.0, 270.0)),
        (20.0, (0.0, 72.0, 28.0, 30.0, 90.0)),
        (20.0, (-70.0, -70.0, 22.0, 35.0, 225.0)),
    ]
    markers = tuple(Marker(80 + k, s, face(*f)) for k, (s, f) in enumerate(sizes_faces))
    return Target("flange-mixed", "DICT_5X5_100", np.array([14.0, -9.0, 61.0]), markers)


class OpenCVPipeline:
    """OpenCV's detector with its sub-pixel refinement on each whole frame, multi-view
    linear triangulation of every corner, a rigid fit of the target."""

    def __init__(self, rig: Rig, target: Target) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.dictionary))
        self.detector = cv2.aruco.ArucoDetector(d, params)
        self.rig = rig
        self.target = target
        self.model = {m.id: m.corners() for m in target.markers}
        self.P = {c.name: np.linalg.inv(c.T_rig_cam)[:3] for c in rig.cameras}

    def reset(self) -> None:
        """A new pose (nothing to forget: every frame is searched whole)."""

    def detect(self, name: str, image: Image) -> tuple[list[Array], Array | None]:
        corners, ids, _ = self.detector.detectMarkers(image)
        return list(corners), ids

    def measure(self, images: dict[str, Image]) -> Array | None:
        rays: dict[tuple[int, int], list[tuple[str, Array]]] = {}
        for cam in self.rig.cameras:
            corners, ids = self.detect(cam.name, images[cam.name])
            if ids is None:
                continue
            for c, i in zip(corners, ids.ravel(), strict=True):
                if int(i) not in self.model:
                    continue
                xy = cv2.undistortPoints(c.reshape(-1, 1, 2), cam.K, cam.dist).reshape(4, 2)
                for k in range(4):
                    rays.setdefault((int(i), k), []).append((cam.name, xy[k]))
        model, measured = [], []
        for (mid, k), obs in rays.items():
            if len(obs) < 2:
                continue
            A = []
            for name, (x, y) in obs:
                P = self.P[name]
                A.append(x * P[2] - P[0])
                A.append(y * P[2] - P[1])
            _, _, vt = np.linalg.svd(np.array(A))
            X = vt[-1]
            measured.append(X[:3] / X[3])
            model.append(self.model[mid][k])
        if len(model) < 3:
            return None
        Pm, Qm = np.array(model), np.array(measured)
        mp, mq = Pm.mean(axis=0), Qm.mean(axis=0)
        R = svd_rotation((Pm - mp).T @ (Qm - mq))
        out: Array = R @ (self.target.reference - mp) + mq
        return out


class WindowedOpenCV(OpenCVPipeline):
    """The honest peer: as :class:`OpenCVPipeline`, but after the first frame each camera
    is searched only in a window around the markers it found in the last frame (cellcal's
    margin), and whole when the window shows none."""

    def __init__(self, rig: Rig, target: Target) -> None:
        super().__init__(rig, target)
        self.last: dict[str, tuple[int, int, int, int]] = {}

    def reset(self) -> None:
        self.last = {}

    def detect(self, name: str, image: Image) -> tuple[list[Array], Array | None]:
        box = self.last.get(name)
        if box is not None:
            h, w = image.shape[:2]
            x0, y0, x1, y1 = max(box[0], 0), max(box[1], 0), min(box[2], w), min(box[3], h)
            corners, ids, _ = self.detector.detectMarkers(image[y0:y1, x0:x1])
            if ids is not None:
                shifted = [c + np.array([x0, y0], np.float32) for c in corners]
                self._remember(name, shifted)
                return shifted, ids
        corners, ids = super().detect(name, image)
        if ids is None:
            self.last.pop(name, None)
        else:
            self._remember(name, corners)
        return corners, ids

    def _remember(self, name: str, corners: list[Array]) -> None:
        pts = np.concatenate([c.reshape(-1, 2) for c in corners])
        lo = np.floor(pts.min(axis=0)).astype(int) - WINDOW_MARGIN_PX
        hi = np.ceil(pts.max(axis=0)).astype(int) + WINDOW_MARGIN_PX
        self.last[name] = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))


def opencv_rig(board: Board, rig: Rig, views: list[dict[str, Image]]) -> Rig:
    """The peer's calibration: ``calibrateCamera`` per camera on its ChArUco corners,
    then ``stereoCalibrate`` of each camera against the first (intrinsics fixed) on the
    corners both saw; the rig frame is the first camera's."""
    pts = board_points(board).astype(np.float32)
    dets = [{n: detect_corners(board, img) for n, img in v.items()} for v in views]
    size = {c.name: (c.width, c.height) for c in rig.cameras}
    intr = {}
    for cam in rig.cameras:
        found = [d for v in dets if (d := v.get(cam.name)) is not None]
        obj = [pts[d.ids] for d in found]
        img = [d.pixels.astype(np.float32) for d in found]
        flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
        _, K, dist, _, _ = cv2.calibrateCamera(obj, img, size[cam.name], None, None, flags=flags)
        intr[cam.name] = (K, dist.ravel()[:5])
    first = rig.cameras[0].name
    out = [Camera(first, *size[first], *intr[first], np.eye(4))]
    for cam in rig.cameras[1:]:
        obj, p0, p1 = [], [], []
        for d in dets:
            a, b = d.get(first), d.get(cam.name)
            if a is None or b is None:
                continue
            ids = np.intersect1d(a.ids, b.ids)
            if len(ids) < 6:
                continue
            obj.append(pts[ids])
            p0.append(a.pixels[np.searchsorted(a.ids, ids)].astype(np.float32))
            p1.append(b.pixels[np.searchsorted(b.ids, ids)].astype(np.float32))
        K0, d0 = intr[first]
        K1, d1 = intr[cam.name]
        r = cv2.stereoCalibrate(
            obj, p0, p1, K0, d0, K1, d1, size[first], flags=cv2.CALIB_FIX_INTRINSIC
        )
        T_cam_first = np.eye(4)
        T_cam_first[:3, :3], T_cam_first[:3, 3] = r[5], r[6].ravel()
        out.append(Camera(cam.name, *size[cam.name], K1, d1, invert(T_cam_first)))
    return Rig("opencv", tuple(out))


def length_errors(measured: list[Array], truth: list[Array]) -> Array:
    """Measured minus true distance between the points of every pair of poses, mm."""
    out = [
        np.linalg.norm(measured[i] - measured[j]) - np.linalg.norm(truth[i] - truth[j])
        for i, j in itertools.combinations(range(len(truth)), 2)
    ]
    return np.array(out)


def texture_series(
    rig: Rig, target: Target, poses: list[Array], frames: int, rng: np.random.Generator
) -> Iterator[tuple[Array, Sets]]:
    """The other renderer's series: each camera's view rendered once per pose (sharp,
    then blurred), then fresh noise and 8-bit quantisation per frame, as its ``render``
    does for one frame."""
    params = tex.RenderParams()
    assert params.psf is not None and params.sensor is not None
    kernel = tex.psf_kernel(params.psf)
    noise = np.float32(params.sensor.noise_grey)
    for T in poses:
        planes = tex.marker_planes(target, T, params)
        blurred = {
            c.name: cv2.filter2D(
                tex.render_clean(c, planes, params), -1, kernel, borderType=cv2.BORDER_REPLICATE
            )
            for c in rig.cameras
        }
        sets = [
            {
                n: np.clip(
                    np.rint(img + noise * rng.standard_normal(img.shape, np.float32)), 0, 255
                ).astype(np.uint8)
                for n, img in blurred.items()
            }
            for _ in range(frames)
        ]
        yield T, sets


@dataclass
class Tally:
    """One pipeline's time and series means on one scene."""

    seconds: float = 0.0
    sets: int = 0
    errors: list[Array] = field(default_factory=list)

    def rate(self) -> float:
        return self.sets / self.seconds

    def rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(np.array(self.errors) ** 2, axis=1))))


def compare(
    rig: Rig,
    target: Target,
    series: Iterator[tuple[Array, Sets]],
    repeat: int,
    extra: Callable[[Array, Sets, Array], None] | None = None,
) -> tuple[dict[str, Tally], list[float], int]:
    """cellcal and both OpenCV pipelines on each series: their time (the least of
    ``repeat`` runs, interleaved: the machine is shared) and errors, cellcal's squared
    Mahalanobis distances per coordinate, and the poses cellcal could not see."""
    meter = TargetMeter(rig, target)
    whole, windowed = OpenCVPipeline(rig, target), WindowedOpenCV(rig, target)
    tally = {k: Tally() for k in ("cellcal", "OpenCV whole-frame", "OpenCV windowed", ALONE)}
    m2: list[float] = []
    skipped = 0
    for T, sets in series:
        truth = T[:3, :3] @ target.reference + T[:3, 3]
        best = dict.fromkeys(tally, np.inf)
        xyz: dict[str, list[Array]] = {}
        try:
            for _ in range(repeat):
                t0 = time.perf_counter()
                mean, _ = meter.series(sets)
                best["cellcal"] = min(best["cellcal"], time.perf_counter() - t0)
                t0 = time.perf_counter()
                meter.reset()
                for s in sets:
                    meter.measure_next(s)
                best[ALONE] = min(best[ALONE], time.perf_counter() - t0)
                for name, peer in (("OpenCV whole-frame", whole), ("OpenCV windowed", windowed)):
                    t0 = time.perf_counter()
                    peer.reset()
                    xyz[name] = [x for x in (peer.measure(s) for s in sets) if x is not None]
                    best[name] = min(best[name], time.perf_counter() - t0)
        except Exception as exc:  # a pose the rig cannot see: reported, not hidden
            print(f"  pose skipped (cellcal): {exc}")
            skipped += 1
            continue
        e = mean.xyz_mm - truth
        m2.append(float(e @ np.linalg.solve(mean.cov_mm2, e)) / 3)
        for name, t in tally.items():
            t.seconds += best[name]
            t.sets += len(sets)
            if name == "cellcal":
                t.errors.append(e)
            elif xyz.get(name):
                t.errors.append(np.mean(xyz[name], axis=0) - truth)
        if extra is not None:
            extra(T, sets, truth)
    return tally, m2, skipped


def report(title: str, tally: dict[str, Tally], m2: list[float], skipped: int, frames: int) -> None:
    ours = tally["cellcal"]
    print(f"{title}: {len(ours.errors)} poses x {frames} frames ({skipped} poses unseen)")
    peers = {k: t for k, t in tally.items() if k.startswith("OpenCV")}
    parts = [f"cellcal {ours.rms():.4f} mm"]
    parts += [f"{k} {t.rms():.4f} mm ({t.rms() / ours.rms():.1f}x)" for k, t in peers.items()]
    print("  3-D error of the series mean (RMS): " + ", ".join(parts))
    print("    (goals: cellcal <= 0.012 mm, >= 10x more accurate than each OpenCV pipeline)")
    print(
        "  predicted covariance vs observed error: mean squared Mahalanobis distance per "
        f"coordinate {np.mean(m2):.2f}"
    )
    goals = {"OpenCV whole-frame": 3.0, "OpenCV windowed": 2.0}
    parts = [f"cellcal {ours.rate():.0f} sets/s"]
    parts += [
        f"{k} {t.rate():.0f} sets/s -> {ours.rate() / t.rate():.2f}x (goal >= {goals[k]:.0f}x)"
        for k, t in peers.items()
    ]
    print("  four-camera sets per second (decoding excluded): " + ", ".join(parts))
    alone, whole = tally[ALONE], peers["OpenCV whole-frame"]
    print(
        f"    (goal: cellcal >= 100 sets/s); each set on its own, as rig measure --sets does: "
        f"{alone.rate():.0f} sets/s -> {alone.rate() / whole.rate():.2f}x whole-frame"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=24, help="poses of the bundled scene")
    ap.add_argument(
        "--other-poses", type=int, default=10, help="poses of each of the other renderer's targets"
    )
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--views", type=int, default=20, help="ChArUco views for the calibration")
    ap.add_argument("--repeat", type=int, default=2, help="timed runs of each series (least)")
    args = ap.parse_args()

    # scene 1, with the calibrated rigs measured beside the perfect one
    rig, target = four_camera_rig(), dome_target()
    board_renderer = SceneRenderer.for_board(
        rig.cameras, BOARD, Optics(supersample=8, blur_px=0.8, noise_grey=2.0)
    )
    board_rng = np.random.default_rng(args.seed + 100)
    views = [
        board_renderer.frames(board_renderer.clean(T), board_rng)
        for T in board_poses(rig, BOARD, args.views, seed=args.seed)
    ]
    sizes = {c.name: (c.width, c.height) for c in rig.cameras}
    options = RigCalibrationOptions(fix_k3=True, fix_tangential=True, holdout_every=0)
    meter_cal = TargetMeter(calibrate_rig(BOARD, sizes, views, options).rig, target)
    peer_cal = OpenCVPipeline(opencv_rig(BOARD, rig, views), target)
    lengths: dict[str, tuple[list[Array], list[Array]]] = {
        k: ([], []) for k in ("cellcal", "opencv")
    }
    truths: list[Array] = []

    def calibrated(T: Array, sets: Sets, truth: Array) -> None:
        truths.append(truth)
        with_cal, _ = meter_cal.series(sets)
        lengths["cellcal"][0].append(with_cal.xyz_mm)
        lengths["cellcal"][1].append(truth)
        xyz = [x for x in (peer_cal.measure(s) for s in sets) if x is not None]
        if xyz:
            lengths["opencv"][0].append(np.mean(xyz, axis=0))
            lengths["opencv"][1].append(truth)

    renderer = SceneRenderer.for_target(rig.cameras, target, Optics(blur_px=0.8, noise_grey=2.0))
    rng = np.random.default_rng(args.seed)
    bundled = (
        (T, [renderer.frames(clean, rng) for _ in range(args.frames)])
        for T in _poses(rng, volume_centre(rig), args.poses)
        for clean in [renderer.clean(T)]
    )
    tally, m2, skipped = compare(rig, target, bundled, args.repeat, calibrated)
    report(
        "photogrammetry, scene 1 (the bundled cell, the camera twin's renderer): 4 cameras "
        "f = 1000 px without distortion, 5 markers of 40 mm (DICT_4X4_50), blur 0.8 px, "
        "noise 2 grey levels",
        tally,
        m2,
        skipped,
        args.frames,
    )
    err = {k: length_errors(*v) for k, v in lengths.items()}
    measured = [t + e for e, t in zip(tally["cellcal"].errors, truths, strict=True)]
    err["perfect"] = length_errors(measured, truths)
    span = np.array([np.linalg.norm(a - b) for a, b in itertools.combinations(truths, 2)])

    def stat(e: Array) -> str:
        return f"{np.sqrt(np.mean(e**2)):.4f} mm RMS (largest {np.abs(e).max():.4f} mm)"

    print(
        f"  length error, {len(err['cellcal'])} pairs of poses, {span.min():.0f}-"
        f"{span.max():.0f} mm (VDI/VDE 2634-1 style), rig calibrated from {args.views} "
        "rendered ChArUco views:"
    )
    print(f"    cellcal, perfect rig:            {stat(err['perfect'])}")
    print(f"    cellcal, rig calibrate:          {stat(err['cellcal'])} (goal <= 0.02 mm RMS)")
    ratio = np.sqrt(np.mean(err["opencv"] ** 2)) / np.sqrt(np.mean(err["cellcal"] ** 2))
    print(f"    OpenCV, stereoCalibrate rig:     {stat(err['opencv'])} -> {ratio:.1f}x cellcal's")

    # scene 2: the other renderer, its rig, two targets
    other = oblique_rig(args.seed)
    for target in (plate_target(), mixed_target()):
        rng = np.random.default_rng([args.seed, len(target.markers), target.markers[0].id])
        poses = target_poses(other, target, args.other_poses, args.seed + 10)
        sizes_mm = ", ".join(f"{m.size:.0f}" for m in target.markers)
        series = texture_series(other, target, poses, args.frames, rng)
        tally, m2, skipped = compare(other, target, series, args.repeat)
        report(
            f"photogrammetry, scene 2 (the other renderer, texture_render.py): its oblique rig, "
            f"fx 1150-1350 px, k1 -0.07..-0.11, target {target.name!r} of {sizes_mm} mm "
            f"({target.dictionary}), defocus 0.7 px + Gaussian 0.5 px, noise 2 grey levels",
            tally,
            m2,
            skipped,
            args.frames,
        )


if __name__ == "__main__":
    main()
