"""The camera rig's drivers: what the measuring code needs of a set of cameras.

A rig grabs *sets*: one image per camera, all triggered together by software, each with
its frame id and two timestamps (the host's clock when it arrived, the camera's own
clock). A camera that misses a frame (lost, incomplete, timed out) is asked again up to
``retries`` times; what was retried is counted, and a camera that still gives nothing is
named in the set as lost, never silently absent.

Backends (``backend`` in the rig's configuration) are rows of a table of the registry
(``CAMERA_BACKENDS`` in ``cellcal/families.py``: the options, the rig class, mock
mode's twin, the libraries): ``aravis`` (GigE Vision and USB3 Vision cameras of any
vendor, opened by address), ``opencv`` (UVC, RTSP and HTTP cameras through
VideoCapture) and ``files`` (recorded image sets: one folder per set, ``<camera>.png``
in each).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Protocol

from numpy.typing import NDArray
from pydantic import Field, model_validator

from cellcal.device_options import Name, Strict
from cellcal.drivers.base import DeviceDescription
from cellcal.families import CAMERA_BACKENDS, camera_backend, load

#: An image as the camera delivers it: (height, width), 8- or 16-bit grey.
Pixels = NDArray[Any]


@dataclass(frozen=True, eq=False)
class Frame:
    """One camera's image of a set: ``frame_id`` as the camera counts, ``host_time`` (s,
    the host's wall clock when the frame arrived), ``device_time`` (s, the camera's own
    timestamp), ``retries`` (grabs repeated for this camera in this set)."""

    camera: str
    image: Pixels
    frame_id: int
    host_time: float
    device_time: float
    retries: int = 0


@dataclass(frozen=True, eq=False)
class FrameSet:
    """One software-triggered set: a frame per camera that answered, and the cameras
    that gave nothing after their retries (``lost``, with the reason)."""

    frames: dict[str, Frame]
    lost: dict[str, str]

    @property
    def retries(self) -> int:
        return sum(f.retries for f in self.frames.values())


class CameraRig(Protocol):
    """A set of synchronised cameras. Every call may raise
    :class:`~cellcal.errors.DeviceError` (with the camera's name and address)."""

    name: str
    #: camera names, in the rig file's order
    cameras: tuple[str, ...]

    def connect(self) -> None:
        """Open every camera by address and configure it (trigger, exposure, gain,
        pixel format, packet size)."""
        ...

    def grab(self) -> FrameSet:
        """Trigger every camera once and collect one frame from each, within the
        configured timeout, retrying lost frames."""
        ...

    def describe(self) -> tuple[DeviceDescription, ...]:
        """Each camera, in the rig file's order: its name (``device``), the backend
        (``family``), its address and what it says of itself (connected)."""
        ...

    def close(self) -> None:
        """Release the cameras; safe to call twice."""
        ...


class CameraOptions(Strict):
    """One camera of a rig: its name (the image's name in a set), its address (a
    backend's own: an IP, a UVC index or URL, a file name), how long one frame may take
    (``timeout_s``) and how often a lost frame is grabbed again (``retries``)."""

    name: Name
    address: str = ""
    timeout_s: Annotated[float, Field(gt=0, le=60)] = 1.0
    retries: Annotated[int, Field(ge=0, le=10)] = 2


class RigOptions(Strict):
    """A camera rig: its name and its backend (a one-value ``Literal`` in each backend's
    subclass, which adds ``cameras``, a non-empty list in the rig file's order)."""

    name: Name = "rig"
    backend: str

    def camera_names(self) -> tuple[str, ...]:
        """The cameras' names, in the rig file's order."""
        return tuple(c.name for c in getattr(self, "cameras", []))

    def endpoint(self) -> str:
        """Where the cameras are, for the campaign's record: their addresses."""
        cameras = getattr(self, "cameras", [])
        return ", ".join(c.address for c in cameras if getattr(c, "address", ""))

    def relative_to(self, folder: Path) -> RigOptions:
        """These options with the paths they hold taken relative to the configuration's
        folder (a backend that holds none: the same options)."""
        return self

    @model_validator(mode="after")
    def _distinct_names(self) -> RigOptions:
        names = [c.name for c in getattr(self, "cameras", [])]
        if len(set(names)) != len(names):
            raise ValueError(f"rig {self.name}: camera names must be distinct: {names}")
        return self


#: The backends a configuration may name: the rows of the registry's table
#: (``CAMERA_BACKENDS`` in ``cellcal/families.py``) that are not mock mode's own.
BACKENDS = tuple(b.name for b in CAMERA_BACKENDS if not b.mock_only)


def rig_class(backend: str) -> Any:
    """The rig class of ``backend`` (it has ``from_options(options, clock=None)``), its
    row of the registry's table imported now with its libraries (a missing one is a
    line naming its extra); also ``rendered``, mock mode's in-process cameras, which a
    configuration cannot name: a twin, handed out by the registry."""
    row = camera_backend(backend)
    if row is None:
        raise KeyError(backend)
    return load(row.rig)
