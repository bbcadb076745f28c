"""The ``files`` camera rig: recorded image sets played back as if grabbed.

``directory`` holds one folder per set, taken in name order; each folder holds one image
per camera, ``<camera>.png`` unless the camera's ``address`` names another file. Images
may be 8- or 16-bit, grey or colour (colour is converted to grey, keeping the depth).
:meth:`FilesRig.grab` returns the next set: a camera whose image is missing, truncated,
unreadable, of another depth or blank (every pixel the same) is in the set's ``lost``
with the reason; after the last set it raises ``DeviceError("no more image sets in
DIR")``. Frame ids count the sets from 1; device time is the image file's modification
time (s); host time the context clock's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from cellcal.calib.photogrammetry.marker_corners import grey
from cellcal.clock import Clock, WallClock
from cellcal.drivers.base import DeviceDescription
from cellcal.drivers.cameras.backends import CameraOptions, Frame, FrameSet, RigOptions
from cellcal.errors import DeviceError, FileFormatError
from cellcal.files.images import Image, set_folders
from cellcal.files.images import read_image as read_image_file

__all__ = ["FilesRig", "FilesRigOptions", "read_image"]


class FilesRigOptions(RigOptions):
    """A rig with ``backend = "files"``: the recording's directory and the cameras
    (``address``: the image's file name in each set, ``<name>.png`` when empty)."""

    backend: Literal["files"] = "files"
    directory: Annotated[str, Field(min_length=1)]
    cameras: Annotated[list[CameraOptions], Field(min_length=1)]

    def endpoint(self) -> str:
        """A recording's folder."""
        return self.directory

    def relative_to(self, folder: Path) -> FilesRigOptions:
        path = Path(self.directory)
        return (
            self
            if path.is_absolute()
            else self.model_copy(update={"directory": str(folder / path)})
        )


def read_image(path: Path) -> tuple[Image | None, str]:
    """(the grey 8/16-bit image, "") or (None, why it cannot be used): a missing,
    truncated or foreign file (cellcal's one image reader), or a blank image."""
    try:
        image = grey(read_image_file(path))
    except FileFormatError as exc:
        return None, str(exc)
    lo, hi = int(image.min()), int(image.max())
    if lo == hi:
        return None, f"{path} is blank (every pixel {lo})"
    return image, ""


class FilesRig:
    """Recorded image sets behind the :class:`~cellcal.drivers.cameras.backends.CameraRig`
    Protocol."""

    def __init__(self, options: FilesRigOptions, *, clock: Clock | None = None) -> None:
        self.name = options.name
        self.options = options
        self.cameras = tuple(c.name for c in options.cameras)
        self.directory = Path(options.directory)
        self.clock = clock or WallClock()
        self._sets: list[Path] = []
        self._next = 0
        self._files = {c.name: c.address or f"{c.name}.png" for c in options.cameras}

    @classmethod
    def from_options(cls, options: FilesRigOptions, clock: Clock | None = None) -> FilesRig:
        return cls(options, clock=clock)

    def connect(self) -> None:
        """List the sets (folders of ``directory``, in name order) and start at the first."""
        if not self.directory.is_dir():
            raise DeviceError(f"rig {self.name}: cannot list {self.directory}: not a directory")
        try:
            sets = set_folders(self.directory)
        except FileFormatError:
            raise DeviceError(f"rig {self.name}: no image sets in {self.directory}") from None
        self._sets, self._next = sets, 0

    @property
    def remaining(self) -> int:
        return len(self._sets) - self._next

    def grab(self) -> FrameSet:
        if not self._sets:
            raise DeviceError(f"rig {self.name}: not connected")
        if self._next >= len(self._sets):
            raise DeviceError(f"no more image sets in {self.directory}")
        folder = self._sets[self._next]
        self._next += 1
        frames: dict[str, Frame] = {}
        lost: dict[str, str] = {}
        for name in self.cameras:
            path = folder / self._files[name]
            image, why = read_image(path)
            if image is None:
                lost[name] = why
                continue
            frames[name] = Frame(
                camera=name,
                image=image,
                frame_id=self._next,
                host_time=self.clock.now(),
                device_time=path.stat().st_mtime,
            )
        return FrameSet(frames=frames, lost=lost)

    def describe(self) -> tuple[DeviceDescription, ...]:
        """Each camera's name and its image's file name in a set: a recording tells
        nothing of the cameras that made it."""
        return tuple(DeviceDescription(n, "files", self._files[n]) for n in self.cameras)

    def close(self) -> None:
        self._sets, self._next = [], 0
