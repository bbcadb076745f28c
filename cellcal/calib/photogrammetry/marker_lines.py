"""A marker's corners from its measured edges: a straight line fitted to each edge's
points in undistorted normalised coordinates (where the pinhole model keeps edges
straight), adjacent lines meeting at the corners; all cameras' markers of a set in one
numpy pass. The edge points come from :mod:`cellcal.calib.photogrammetry.marker_corners`.

Pure numerics: edge points and a :class:`~cellcal.calib.photogrammetry.camera_rig.Camera` in,
corners
in normalised coordinates out.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.camera_rig import Camera
from cellcal.calib.photogrammetry.marker_corners import MIN_EDGE_POINTS, MarkerImage, row_median

Image = NDArray[Any]


@dataclass(frozen=True, eq=False)
class MarkerCorners:
    """A marker's corners in one camera: undistorted normalised coordinates (4, 2) in the
    detector's order, and the RMS distance of the edge points from their lines (px)."""

    id: int
    xy: Array
    edge_rms_px: float


def marker_corners(camera: Camera, markers: list[MarkerImage]) -> list[MarkerCorners]:
    """The corners where each marker's fitted edge lines meet, in normalised
    coordinates. A marker whose edge cannot be fitted, or whose adjacent edges are within
    3° of parallel, is left out."""
    return marker_corners_many([camera], [markers])[0]


def marker_corners_many(
    cameras: Sequence[Camera], markers: Sequence[list[MarkerImage]]
) -> list[list[MarkerCorners]]:
    """:func:`marker_corners` for several cameras' markers at once (one set)."""
    every = [mk for found in markers for mk in found]
    if not every:
        return [[] for _ in markers]
    n_j = max(mk.points_px.shape[1] for mk in every)
    pts = np.concatenate([_pad(mk.points_px, n_j) for mk in every])
    mask = np.concatenate([_pad(mk.measured, n_j) for mk in every])
    i = 0
    for camera, found in zip(cameras, markers, strict=True):
        if found:
            f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
            block, sel = pts[4 * i : 4 * (i + len(found))], mask[4 * i : 4 * (i + len(found))]
            block[sel] = _normalised(camera, block[sel]) * f  # px-sized units keep the fit scaled
            i += len(found)
    normal, c, rms, ok = _fit_lines(pts, mask)
    x, y, det = _meet(normal, c)
    good: Image = np.asarray(ok.reshape(-1, 4).all(axis=1) & (np.abs(det) >= 0.05).all(axis=1))
    rms_m = np.sqrt((rms.reshape(-1, 4) ** 2).mean(axis=1)).tolist()
    xy = np.stack([x, y], axis=2)
    out: list[list[MarkerCorners]] = []
    i = 0
    for camera, found in zip(cameras, markers, strict=True):
        mine = xy[i : i + len(found)] / float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
        out.append(
            [
                MarkerCorners(mk.id, mine[k], rms_m[i + k])
                for k, mk in enumerate(found)
                if good[i + k]
            ]
        )
        i += len(found)
    return out


def _meet(normal: Array, c: Array) -> tuple[Array, Array, Array]:
    """Where each marker's adjacent edge lines ``n·p = c`` meet: corner k on edges k − 1
    and k, (m, 4) each of x and y, and the determinant (the sine of their angle)."""
    n1, c1 = np.roll(normal.reshape(-1, 4, 2), 1, axis=1), np.roll(c.reshape(-1, 4), 1, axis=1)
    n2, c2 = normal.reshape(-1, 4, 2), c.reshape(-1, 4)
    det = n1[..., 0] * n2[..., 1] - n1[..., 1] * n2[..., 0]
    safe = np.where(np.abs(det) < 1e-12, 1.0, det)
    x = (c1 * n2[..., 1] - c2 * n1[..., 1]) / safe
    y = (n1[..., 0] * c2 - n2[..., 0] * c1) / safe
    return x, y, det


def _pad(a: Image, n_j: int) -> Image:
    """``a`` (4, J, ...) padded with zeros to (4, n_j, ...)."""
    if a.shape[1] == n_j:
        return a
    width = [(0, 0), (0, n_j - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
    return np.pad(a, width)


def _normalised(camera: Camera, pixels: Array) -> Array:
    """Undistorted normalised coordinates (n, 2) of pixel positions (n, 2): OpenCV's
    fixed-point iteration, as many times as this camera's lens needs (:func:`_iterations`;
    its ε test costs as much again and is never met at 1e-14)."""
    uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT, _iterations(camera), 0.0)
    xy = cv2.undistortPoints(uv, camera.K, camera.dist, criteria=criteria)
    out: Array = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return out


_ITERATIONS: weakref.WeakKeyDictionary[Camera, int] = weakref.WeakKeyDictionary()


def _iterations(camera: Camera) -> int:
    """The fewest iterations (5, 10, 20, 40 or 100) of OpenCV's undistortion that bring
    every pixel of this camera's image within 1e-6 px of 200 iterations (cached a camera:
    at f = 1000 px in 1280×1024: 10 for k1 = −0.1 or −0.2, 20 for −0.3)."""
    n = _ITERATIONS.get(camera)
    if n is None:
        grid = np.mgrid[0 : camera.width - 1 : 9j, 0 : camera.height - 1 : 9j]
        uv = grid.reshape(2, -1).T.reshape(-1, 1, 2)
        f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
        solve = [
            cv2.undistortPoints(uv, camera.K, camera.dist, criteria=(1, k, 0.0)) * f
            for k in (5, 10, 20, 40, 200)
        ]
        n = next(
            k
            for k, xy in zip((5, 10, 20, 40, 100), solve, strict=True)
            if k == 100 or np.abs(xy - solve[-1]).max() < 1e-6
        )
        _ITERATIONS[camera] = n
    return n


def _fit_lines(pts: Array, mask: Image) -> tuple[Array, Array, Array, Image]:
    """Total-least-squares lines ``n·p = c`` through padded point sets (E, J, 2), three
    passes dropping points beyond 3 robust σ; (normals, offsets, RMS residuals, fitted)."""
    keep = mask.copy()
    for _ in range(3):
        wgt = keep.astype(np.float64)
        cnt = np.maximum(wgt.sum(axis=1), 1.0)
        mu = (wgt[:, None, :] @ pts)[:, 0] / cnt[:, None]
        q = (pts - mu[:, None, :]) * wgt[..., None]
        s = q.transpose(0, 2, 1) @ q  # scatter (E, 2, 2)
        theta = 0.5 * np.arctan2(2 * s[:, 0, 1], s[:, 0, 0] - s[:, 1, 1])  # the direction
        normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
        c = (normal * mu).sum(axis=1)
        r = (pts @ normal[:, :, None])[..., 0] - c[:, None]
        mad = 1.4826 * row_median(np.where(keep, np.abs(r), np.nan))
        new = mask & (np.abs(r) <= np.maximum(3.0 * mad, 1e-9)[:, None])
        if np.array_equal(new, keep):
            break
        keep = new
    n_kept = keep.sum(axis=1)
    rms = np.sqrt(np.where(keep, r**2, 0.0).sum(axis=1) / np.maximum(n_kept, 1))
    return normal, c, rms, n_kept >= MIN_EDGE_POINTS
