"""Measuring the target frame after frame: find its markers where it was last seen, and
the mean of a series (a pose's dwell) with its uncertainty.

A series is a still target filmed 20 times. The first frame is searched whole with the
detector (the target located at half resolution, then searched in its window at full
resolution: :class:`~cellcal.calib.photogrammetry.marker_corners.MarkerFinder`). In each next
frame the
markers a camera saw are followed: their edges are measured where the last pose projects
them, without the detector, and the last pose starts the fit. Where a followed marker is
not found, the detector searches a window around the expected markers (with a margin),
once a series for each camera: a marker lost again after that is left out of that frame
and followed in the next (one at the limit of what can be measured costs no detector
run a frame). Where a camera loses every marker, the whole image is searched; a camera
whose whole image showed no marker is not searched again while the target holds still;
a fit from the last pose that leaves a large residual is started afresh. A target that
moved is found again, not lost. :meth:`TargetMeter.reset` forgets everything: a set
measured after it gives the numbers it gives alone. :meth:`TargetMeter.measure_next`
measures a batch of sets that may be of several poses (``rig measure --sets``):
followed while the target stays, afresh when it does not.

The mean's covariance is given two ways: propagated (the frames' covariances averaged
and divided by n, plus the detector's floor :data:`CORNER_FLOOR_PX`, which does not
average) and observed (the frames' scatter divided by n, which sees no floor). Neither
sees a wrong calibration of the rig.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.calib.photogrammetry.marker_corners import (
    Image,
    MarkerFinder,
    MarkerImage,
    Window,
)
from cellcal.calib.photogrammetry.marker_lines import marker_corners_many
from cellcal.calib.photogrammetry.target_pose import TargetPose, measure_target, target_corners
from cellcal.errors import InputError, MeasurementError

#: Margin around the predicted markers of a search window, px.
WINDOW_MARGIN_PX = 24
#: The part of a corner's error that does not average over frames of a still target,
#: per image coordinate, px (the detector's and the renderer's bias together): the value
#: for which the series means' squared Mahalanobis distance per coordinate averages 1
#: on the camera twin's images (blur 0.8 px, noise 2 grey levels, 80 series of 20
#: frames in two independent draws: 0.0093 and 0.0082 px). Noise-free images would
#: overstate it (0.014 px): without noise the grey levels' quantisation is not dithered.
#: A real rig adds its calibration's error, which no covariance here contains.
CORNER_FLOOR_PX = 0.009
#: A fit started from the last pose that leaves more than this RMS is started afresh.
RESTART_RMS_PX = 1.0


@dataclass(frozen=True, eq=False)
class SeriesMean:
    """The mean of a series of frames of a still target (rig frame, mm)."""

    xyz_mm: Array
    #: covariance of the mean, propagated from each frame's covariance (mm²)
    cov_mm2: Array
    #: covariance of the mean from the frames' scatter (mm²; zeros for one frame)
    scatter_cov_mm2: Array
    T_rig_target: Array
    n: int
    #: frames that gave no measurement, as "frame k: reason"
    failures: tuple[str, ...]


class TargetMeter:
    """Measures one target with one rig, frame after frame."""

    def __init__(self, rig: Rig, target: Target, *, min_cameras: int = 2) -> None:
        self.rig = rig
        self.target = target
        self.min_cameras = min_cameras
        self._corners = target_corners(target)
        every = np.concatenate(list(self._corners.values()))
        extent = {
            m.id: (
                m.size,
                float(np.linalg.norm(every - self._corners[m.id].mean(axis=0), axis=1).max()),
            )
            for m in target.markers
        }
        self._finder = MarkerFinder(target.dictionary, frozenset(extent), extent)
        self._forget()

    def _forget(self) -> None:
        self._strict = False  # measure_next: a set that is not followed whole is redone
        self._last: TargetPose | None = None
        self._seen: dict[str, list[int]] = {}
        self._blind: set[str] = set()  # cameras whose last whole search found nothing
        self._searched: set[str] = set()  # cameras searched in a window since then

    def reset(self) -> None:
        """Forget the last pose: the next frame is searched whole (a new robot pose), and
        measured as if it were the first (the same images give the same numbers)."""
        self._forget()

    def measure(self, images: Mapping[str, Image]) -> TargetPose:
        """The target in one set of images (camera name → image)."""
        unknown = sorted(set(images) - {c.name for c in self.rig.cameras})
        if unknown:
            raise InputError(f"images of cameras not in rig {self.rig.name!r}: {unknown}")
        cams = [c for c in self.rig.cameras if c.name in images]
        found = self._find({c.name: images[c.name] for c in cams})
        corners = marker_corners_many(cams, [found[c.name] for c in cams])
        views = {c.name: v for c, v in zip(cams, corners, strict=True)}
        start = None if self._last is None else self._last.T_rig_target
        try:
            pose = measure_target(
                self.rig, self.target, views, min_cameras=self.min_cameras, start=start
            )
            if start is not None and pose.reprojection_rms_px > RESTART_RMS_PX:
                if self._strict:
                    raise _Moved
                # the target moved: fit again from each camera's own estimate, and look
                # again everywhere next time
                self._blind.clear()
                self._searched.clear()
                pose = measure_target(self.rig, self.target, views, min_cameras=self.min_cameras)
        except MeasurementError:
            self._forget()
            raise
        self._last = pose
        return pose

    def measure_next(self, images: Mapping[str, Image]) -> TargetPose:
        """One set of a batch whose sets may show one pose or several (``rig measure
        --sets``): followed from the last set when every marker the last set saw is found
        again where the last pose puts it, and the fit is as good; otherwise measured
        afresh, as after :meth:`reset`. A set's numbers are its own either way (following
        only starts the search and the fit where the last set ended; it averages
        nothing); they differ from a fresh search by the edges' convergence, a few
        micrometres."""
        if self._last is None:
            return self.measure(images)
        self._strict = True
        try:
            return self.measure(images)
        except _Moved:
            self.reset()
            return self.measure(images)
        finally:
            self._strict = False

    def series(self, sets: list[Mapping[str, Image]]) -> tuple[SeriesMean, list[TargetPose]]:
        """The mean of a series of sets of a still target; frames that fail are named
        in ``failures``; fewer than two good frames is a :class:`MeasurementError`."""
        self.reset()
        poses: list[TargetPose] = []
        failures: list[str] = []
        for k, images in enumerate(sets):
            try:
                poses.append(self.measure(images))
            except MeasurementError as exc:
                failures.append(f"frame {k}: {exc}")
        if not poses:
            raise MeasurementError(
                f"no frame of the series measured the target ({failures[0] if failures else ''})"
            )
        return mean_of(poses, tuple(failures)), poses

    def _expected(self, cam_name: str) -> tuple[list[int], Array] | None:
        """The markers this camera saw in the last frame and where the last pose puts
        their corners now, (m, 4, 2) px; None without a last pose."""
        pose = self._last
        if pose is None or not self._seen.get(cam_name):
            return None
        cam = self.rig.camera(cam_name)
        T = pose.T_rig_target
        ids = self._seen[cam_name]
        pts = np.concatenate([self._corners[i] for i in ids]) @ T[:3, :3].T + T[:3, 3]
        return ids, cam.project(pts).reshape(-1, 4, 2)

    def _find(self, images: dict[str, Image]) -> dict[str, list[MarkerImage]]:
        """Follow the markers each camera saw last time (all cameras at once); where
        they are not all found, detect in a window around them, and where nothing is
        found there either, in the whole image. A camera whose whole image showed no
        marker is not searched again while the target holds still (a target hidden
        from one camera costs that camera one search per series), nor is one that
        loses a marker again once a window search has been made (a marker at the limit
        of what can be measured: left out of that frame, followed again in the next)."""
        expected = {n: e for n in images if (e := self._expected(n)) is not None}
        names = list(expected)
        followed = self._finder.follow_many(
            [images[n] for n in names], [expected[n] for n in names]
        )
        found = dict(zip(names, followed, strict=True))
        if self._strict and any(len(found[n]) < len(expected[n][0]) for n in names):
            raise _Moved
        others = [n for n in images if n not in expected]
        whole = [n for n in others if self._last is None or n not in self._blind]
        searched = self._finder.find_many([images[n] for n in whole], [None] * len(whole))
        for name in others:
            found[name] = searched[whole.index(name)] if name in whole else []
            if not found[name]:
                self._blind.add(name)
            self._seen[name] = [m.id for m in found[name]]
        for name, image in images.items():
            if name not in expected:
                continue
            ids, corners = expected[name]
            if len(found[name]) == len(ids):
                continue
            if found[name] and name in self._searched:
                continue  # lost again: left out of this frame, still followed
            self._searched.add(name)
            near = self._finder.find(image, _around(corners))
            if not near and not found[name]:
                near = self._finder.find(image)  # the target moved out of its window
                self._blind.clear()
                if not near:
                    self._blind.add(name)
            if len(near) > len(found[name]):
                found[name] = near
            self._seen[name] = [m.id for m in found[name]]
        return found


class _Moved(Exception):  # noqa: N818 - a signal inside measure_next, never raised out
    """The set in :meth:`TargetMeter.measure_next` is not where the last one was."""


def _around(corners_px: Array) -> Window:
    """The window around markers' corners (m, 4, 2), with the search margin."""
    lo = np.floor(corners_px.reshape(-1, 2).min(axis=0)).astype(int) - WINDOW_MARGIN_PX
    hi = np.ceil(corners_px.reshape(-1, 2).max(axis=0)).astype(int) + WINDOW_MARGIN_PX
    return Window(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))


def mean_of(poses: list[TargetPose], failures: tuple[str, ...] = ()) -> SeriesMean:
    """The mean reference point and pose of frames of a still target."""
    n = len(poses)
    xyz = np.array([p.xyz_mm for p in poses])
    # noise averages over the frames; the detector's floor does not
    floor = [p.cov_mm2 * min((CORNER_FLOOR_PX / p.sigma_px) ** 2, 1.0) for p in poses]
    cov = np.mean([p.cov_mm2 for p in poses], axis=0) / n + np.mean(floor, axis=0)
    scatter = np.cov(xyz.T, ddof=1) / n if n > 1 else np.zeros((3, 3))
    # the chordal mean of the rotations: the nearest rotation to their average
    u, _, vt = np.linalg.svd(np.mean([p.T_rig_target[:3, :3] for p in poses], axis=0))
    R = u @ np.diag([1.0, 1.0, float(np.linalg.det(u @ vt))]) @ vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.mean([p.T_rig_target[:3, 3] for p in poses], axis=0)
    return SeriesMean(xyz.mean(axis=0), cov, scatter, T, n, failures)
