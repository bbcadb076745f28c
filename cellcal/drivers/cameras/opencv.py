"""The ``opencv`` camera rig: cameras OpenCV's VideoCapture can open (a UVC device by its
index, an RTSP or HTTP/MJPEG URL, or a video file or image sequence for tests and
playback).

Limits, honestly: there is no trigger. A set is one fresh frame read from each camera in
turn, so the cameras of a set are not simultaneous (a moving target is seen at different
instants: keep the robot still while grabbing), and a network camera's frames lag by its
own buffering (MJPEG 1–2 frames). ``flush`` frames are read and dropped before the one
kept, to get past frames that waited in a buffer. Timeouts (``timeout_s``) hold for
FFmpeg sources (RTSP, HTTP, files); V4L2 devices have their driver's own. Pixels are
converted to grey; frame ids are the rig's own count per camera from 1; device time is
the source's position (``CAP_PROP_POS_MSEC``, s) and host time the context clock's.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import Field

from cellcal.calib.photogrammetry.marker_corners import grey
from cellcal.clock import Clock, WallClock
from cellcal.drivers.base import DeviceDescription, label
from cellcal.drivers.cameras.backends import CameraOptions, Frame, FrameSet, RigOptions
from cellcal.errors import DeviceError

__all__ = ["OpenCVCameraOptions", "OpenCVRig", "OpenCVRigOptions"]

log = logging.getLogger("cellcal.cameras.opencv")


class OpenCVCameraOptions(CameraOptions):
    """One VideoCapture camera: ``address`` a UVC index ("0"), an ``rtsp://`` or
    ``http://`` URL, or a file; frames to drop before each kept one (``flush``)."""

    address: Annotated[str, Field(min_length=1)]
    flush: Annotated[int, Field(ge=0, le=30)] = 0


class OpenCVRigOptions(RigOptions):
    """A rig with ``backend = "opencv"``."""

    backend: Literal["opencv"] = "opencv"
    cameras: Annotated[list[OpenCVCameraOptions], Field(min_length=1)]


def _open(address: str, timeout_s: float) -> Any:
    ms = int(timeout_s * 1000)
    if address.isdigit():
        cap = cv2.VideoCapture(int(address), cv2.CAP_ANY)
    else:
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
        cap = cv2.VideoCapture(address, cv2.CAP_ANY, params)
    cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # where the backend can: keep the newest frame only
    return cap


class OpenCVRig:
    """VideoCapture cameras behind the :class:`~cellcal.drivers.cameras.backends.CameraRig`
    Protocol."""

    def __init__(self, options: OpenCVRigOptions, *, clock: Clock | None = None) -> None:
        self.name = options.name
        self.options = options
        self.cameras = tuple(c.name for c in options.cameras)
        self.clock = clock or WallClock()
        self._captures: dict[str, Any] = {}
        self._counts: dict[str, int] = {}

    @classmethod
    def from_options(cls, options: OpenCVRigOptions, clock: Clock | None = None) -> OpenCVRig:
        return cls(options, clock=clock)

    def connect(self) -> None:
        self.close()
        for cam in self.options.cameras:
            cap = _open(cam.address, cam.timeout_s)
            if not cap.isOpened():
                cap.release()
                self.close()
                where = label(f"camera {cam.name}", cam.address)
                raise DeviceError(f"{where}: cannot open (no such device, URL or file)")
            self._captures[cam.name] = cap
            self._counts[cam.name] = 0

    def _read(self, cam: OpenCVCameraOptions) -> tuple[np.ndarray[Any, Any] | None, str]:
        cap = self._captures[cam.name]
        for _ in range(cam.flush):
            cap.grab()
        ok, image = cap.read()
        if not ok or image is None or image.size == 0:
            return None, "no frame (end of stream, or the camera does not answer)"
        if image.dtype not in (np.uint8, np.uint16):
            return None, f"{image.dtype} pixels (8- or 16-bit expected)"
        return grey(image), ""

    def grab(self) -> FrameSet:
        if not self._captures:
            raise DeviceError(f"rig {self.name}: not connected")
        frames: dict[str, Frame] = {}
        lost: dict[str, str] = {}
        for cam in self.options.cameras:
            reason = ""
            for attempt in range(cam.retries + 1):
                image, reason = self._read(cam)
                if image is None:
                    continue
                self._counts[cam.name] += 1
                frames[cam.name] = Frame(
                    camera=cam.name,
                    image=np.ascontiguousarray(image),
                    frame_id=self._counts[cam.name],
                    host_time=self.clock.now(),
                    device_time=self._captures[cam.name].get(cv2.CAP_PROP_POS_MSEC) / 1000.0,
                    retries=attempt,
                )
                break
            else:
                lost[cam.name] = f"{reason} after {cam.retries + 1} attempt(s)"
                log.warning("%s: %s", label(f"camera {cam.name}", cam.address), lost[cam.name])
        return FrameSet(frames=frames, lost=lost)

    def describe(self) -> tuple[DeviceDescription, ...]:
        """Each camera's name and address: VideoCapture tells nothing of the device."""
        return tuple(DeviceDescription(c.name, "opencv", c.address) for c in self.options.cameras)

    def close(self) -> None:
        for cap in self._captures.values():
            cap.release()
        self._captures.clear()
        self._counts.clear()
