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

from cellcal.calib.camera_rig import Board
from cellcal.calib.geometry import Array
from cellcal.calib.marker_corners import grey
from cellcal.errors import InputError, MeasurementError

Image = NDArray[Any]

#: At most this many images are tried again (flipped, other pattern) to name a mistake.
_TRIES = 12


@dataclass(frozen=True, eq=False)
class CornerDetection:
    """ChArUco corners found in one image: their ids (n,) and pixel positions (n, 2)."""

    ids: NDArray[np.int64]
    pixels: Array


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
    corners, ids, _, _ = det.detectBoard(grey8(image))
    if ids is None or len(ids) < min_corners:
        return None
    ids = np.asarray(ids, dtype=np.int64).ravel()
    obj = board_points(board)[ids][:, :2]
    centred = obj - obj.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(len(ids))
    if spread < 0.25 * board.square:
        return None
    return CornerDetection(ids, np.asarray(corners, dtype=np.float64).reshape(-1, 2))


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
