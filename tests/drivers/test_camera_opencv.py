"""The ``opencv`` rig through VideoCapture, on file-backed sources: a short MJPEG video
and a PNG image sequence written here with cv2 (no camera, no network). Each set reads
the next frame of each source; the end of a source makes that camera lost."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cellcal.drivers.cameras.backends import rig_class
from cellcal.drivers.cameras.opencv import OpenCVRig, OpenCVRigOptions
from cellcal.errors import DeviceError

pytestmark = pytest.mark.timeout(30)

N = 5


def frame(k: int) -> np.ndarray:
    """Frame k: a grey ramp with a 16×16 block of level 40 k + 20 at column 8 k."""
    yy, xx = np.mgrid[0:96, 0:128]
    img = ((xx + yy) % 64).astype(np.uint8)
    img[40:56, 8 * k : 8 * k + 16] = 40 * k + 20
    return img


@pytest.fixture
def video(tmp_path: Path) -> str:
    path = tmp_path / "cam.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (128, 96))
    assert out.isOpened()
    for k in range(N):
        out.write(cv2.cvtColor(frame(k), cv2.COLOR_GRAY2BGR))
    out.release()
    return str(path)


@pytest.fixture
def sequence(tmp_path: Path) -> str:
    for k in range(N):
        cv2.imwrite(str(tmp_path / f"img_{k:03d}.png"), frame(k))
    return str(tmp_path / "img_%03d.png")


def connect(**cameras: str) -> OpenCVRig:
    cams = [{"name": n, "address": a, "retries": 1} for n, a in cameras.items()]
    rig = OpenCVRig(OpenCVRigOptions.model_validate({"cameras": cams}))
    rig.connect()
    return rig


def test_each_set_reads_the_next_frame_of_each_camera(video: str, sequence: str) -> None:
    rig = connect(movie=video, stills=sequence)
    assert rig_class("opencv") is OpenCVRig
    for k in range(N):
        s = rig.grab()
        assert s.lost == {}
        stills, movie = s.frames["stills"], s.frames["movie"]
        assert np.array_equal(stills.image, frame(k))  # PNG: exact
        assert movie.image.shape == (96, 128) and movie.image.dtype == np.uint8
        block = movie.image[42:54, 8 * k + 2 : 8 * k + 14].astype(float)
        assert abs(block.mean() - (40 * k + 20)) < 6  # MJPEG: lossy
        assert stills.frame_id == movie.frame_id == k + 1
    end = rig.grab()
    assert end.frames == {} and set(end.lost) == {"movie", "stills"}
    assert (
        "no frame (end of stream" in end.lost["movie"] and "after 2 attempt(s)" in end.lost["movie"]
    )
    rig.close()
    rig.close()


def test_flush_drops_frames_before_the_kept_one(sequence: str) -> None:
    cams = [{"name": "a", "address": sequence, "flush": 1}]
    rig = OpenCVRig(OpenCVRigOptions.model_validate({"cameras": cams}))
    rig.connect()
    assert np.array_equal(rig.grab().frames["a"].image, frame(1))
    assert np.array_equal(rig.grab().frames["a"].image, frame(3))
    rig.close()


def test_a_source_that_does_not_open_is_one_device_error_line(tmp_path: Path) -> None:
    with pytest.raises(DeviceError) as err:
        connect(ghost=str(tmp_path / "absent.avi"))
    assert (
        str(err.value)
        == f"camera ghost at {tmp_path / 'absent.avi'}: cannot open (no such device, URL or file)"
    )
