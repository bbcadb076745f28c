"""ChArUco corners in images of a calibration board, and the reason when a board is not
found where it should be.

Detection is OpenCV's ``CharucoDetector``; a detection with fewer than ``min_corners``
corners, or with all of them on one line, is no detection. When images show no board,
two mistakes are told apart from a wrong board file:

* the other ``legacy`` pattern (boards made before OpenCV 4.6 with an even number of
  rows differ);
* a mirrored image: a camera with ``ReverseX`` or ``ReverseY`` set, or a board seen
  through from its back (a glass board turned over). A mirrored ArUco marker is not a
  marker, so such an image shows no board until it is flipped back.

Pure numerics: images (numpy arrays) in, corner ids and pixels out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.board_edges import BoardEdges
from cellcal.calib.photogrammetry.camera_rig import Board
from cellcal.calib.photogrammetry.marker_corners import grey, grey_levels
from cellcal.errors import InputError, MeasurementError

Image = NDArray[Any]

#: At most this many images are tried again (flipped, other pattern) to name a mistake.
_TRIES = 12


@dataclass(frozen=True, eq=False)
class CornerDetection:
    """ChArUco corners found in one image: their ids (n,) and pixel positions (n, 2);
    ``markers``, the detector's ArUco markers (corners, ids, as OpenCV gives them) the
    corners came from, where kept: a second detection in the same image starts from
    them instead of finding them again (:meth:`CornerMeter.measure`)."""

    ids: NDArray[np.int64]
    pixels: Array
    markers: tuple[Any, Any] | None = None


def grey8(image: Image) -> Image:
    """An 8-bit grey image from 8/16-bit grey or colour (BGR/BGRA) data; 16-bit data are
    scaled so that their brightest pixel becomes 255."""
    img = grey(image)
    if img.ndim != 2:
        raise InputError(f"image: expected a grey or colour image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img
    top = max(float(img.max()), 1.0)
    out: Image = np.clip(np.rint(img.astype(np.float64) * (255.0 / top)), 0, 255).astype(np.uint8)
    return out


def board_points(board: Board) -> Array:
    """The chessboard's inner corners (n, 3) in the board frame, mm, by id."""
    return np.asarray(board.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


def detect_corners(
    board: Board, image: Image, min_corners: int = 6, detector: Any = None
) -> CornerDetection | None:
    """The board's chessboard corners in ``image``; None when fewer than
    ``min_corners`` are found or all of them lie on one line."""
    det = detector or cv2.aruco.CharucoDetector(board.cv_board())
    corners, ids, marker_corners, marker_ids = det.detectBoard(grey8(image))
    if ids is None or len(ids) < min_corners:
        return None
    ids = np.asarray(ids, dtype=np.int64).ravel()
    if not _spread(board, ids):
        return None
    pixels = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    return CornerDetection(ids, pixels, (marker_corners, marker_ids))


def _spread(board: Board, ids: NDArray[np.int64]) -> bool:
    """Whether the corners ``ids`` span the board in two directions (not one line)."""
    obj = board_points(board)[ids][:, :2]
    centred = obj - obj.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(len(ids))
    return bool(spread >= 0.25 * board.square)


class CornerMeter:
    """The board's corners measured again with a camera's first calibration: OpenCV's
    detector given the intrinsics (its corners start from the board's pose, through the
    lens's distortion), then each corner from its edges
    (:class:`~cellcal.calib.photogrammetry.board_edges.BoardEdges`). Corners whose edges cannot be
    measured are left out one by one; a view keeps its detection only while
    ``min_corners`` remain, spread over the board."""

    def __init__(self, board: Board, K: Array, dist: Array, min_corners: int = 6) -> None:
        self.board = board
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64)
        self.min_corners = min_corners
        self.edges = BoardEdges(board)
        self.points = board_points(board)
        params = cv2.aruco.CharucoParameters()
        params.cameraMatrix = self.K
        params.distCoeffs = self.dist
        self.detector = cv2.aruco.CharucoDetector(board.cv_board())
        self.detector.setCharucoParameters(params)
        #: corners the detector found whose edges could not be measured, so far
        self.unmeasured = 0

    def measure(self, image: Image, first: CornerDetection | None = None) -> CornerDetection | None:
        """The corners in ``image``; None when too few are measured. ``first``, this
        image's detection by :func:`detect_corners`: its markers are taken as they are
        (finding them is nearly all of a detection's time; the intrinsics change only
        how the chessboard corners are found between them)."""
        grey8_, levels = grey_levels(image)
        if first is not None and first.markers is not None:
            marker_corners, marker_ids = first.markers
            corners, ids, _, _ = self.detector.detectBoard(
                grey8_, markerCorners=marker_corners, markerIds=marker_ids
            )
        else:
            corners, ids, _, _ = self.detector.detectBoard(grey8_)
        if ids is None or len(ids) < self.min_corners:
            return None
        ids = np.asarray(ids, dtype=np.int64).ravel()
        px = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        ok, rvec, tvec = cv2.solvePnP(self.points[ids], px, self.K, self.dist)
        if not ok:
            return None
        refined = self.edges.refine(
            levels, self.K, self.dist, np.asarray(rvec, float), np.asarray(tvec, float), ids
        )
        self.unmeasured += len(refined.unmeasured)
        if len(refined.ids) < self.min_corners or not _spread(self.board, refined.ids):
            return None
        return CornerDetection(refined.ids, refined.pixels)


def shows_mirrored(board: Board, image: Image, min_corners: int = 6, detector: Any = None) -> bool:
    """Whether ``image`` flipped left to right shows the board (a flip up and down is the
    same up to a half turn, which the board's ids undo)."""
    flipped = np.ascontiguousarray(grey8(image)[:, ::-1])
    return detect_corners(board, flipped, min_corners, detector) is not None


def mirrored_count(board: Board, images: Sequence[Image], min_corners: int = 6) -> int:
    """How many of the first images tried show the board mirrored."""
    det = cv2.aruco.CharucoDetector(board.cv_board())
    return sum(shows_mirrored(board, img, min_corners, det) for img in images[:_TRIES])


def board_not_found(board: Board, images: Sequence[Image], min_corners: int) -> MeasurementError:
    """The refusal when no image shows the board, naming a mirrored image or the other
    ``legacy`` pattern when either is what the images show."""
    if mirrored_count(board, images, min_corners):
        return MeasurementError(
            "board found only in mirrored images — is ReverseX or ReverseY set on the "
            "cameras, or is the board seen through from its back?"
        )
    other = Board(board.dictionary, board.squares, board.square, board.marker, not board.legacy)
    det = cv2.aruco.CharucoDetector(other.cv_board())
    for img in images[:_TRIES]:
        if detect_corners(other, img, min_corners, det) is not None:
            return MeasurementError(
                f"board not found in any view — is `legacy` right? (the images show a "
                f"board with legacy = {str(other.legacy).lower()})"
            )
    return MeasurementError(
        "board not found in any view — is `legacy` right? (check also the board's "
        "dictionary, squares and marker sizes)"
    )
