"""The first ChArUco detection of each image, kept for the test module that calibrates
the same rendered views again and again (each calibration detects every image anew,
about 25 ms an image: seconds per calibration). Detection is deterministic, so a
detection kept is the detection made: the image's bytes, shape and type, the board and
the minimum number of corners are the key, and what is kept is read-only (a
calibration that wrote into it would fail, not share a changed result)."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from cellcal.calib.photogrammetry import rig_calibration
from cellcal.calib.photogrammetry.board_corners import CornerDetection, detect_corners


def kept_detections() -> Iterator[dict[tuple[Any, ...], CornerDetection | None]]:
    """For a module fixture: ``rig_calibration.detect_corners`` keeps its answers while
    the module's tests run; the detections kept, by key."""
    kept: dict[tuple[Any, ...], CornerDetection | None] = {}

    def detect(board: Any, image: Any, min_corners: int = 6, detector: Any = None) -> Any:
        data = np.ascontiguousarray(image)
        key = (repr(board), data.shape, data.dtype.str, min_corners,
               hashlib.blake2b(data.data, digest_size=16).digest())  # fmt: skip
        if key not in kept:
            found = detect_corners(board, image, min_corners, detector)
            if found is not None:
                found.ids.setflags(write=False)
                found.pixels.setflags(write=False)
            kept[key] = found
        return kept[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(rig_calibration, "detect_corners", detect)
        yield kept
