"""The photogrammetry rig as a campaign sensor: cameras grab sets, each set measures the
target (``calib/photogrammetry/rig_measurement.py``), a pose's series carries every set's reference
point with its covariance and the target's orientation.

Configured as a ``[[sensor]]`` with ``kind = "photogrammetry"`` and ``driver =
"cameras"``: the rig file (``rig calibrate --out``), the target file, and under
``[sensor.capture]`` the cameras (a backend's options, ``docs/cameras.md``). A series of
``n`` samples at one pose triggers sets at ``rate_hz`` until ``n`` of them measured the
target, at most ``2 n`` sets: a set whose target is not measured (seen by fewer than
``min_cameras``) is left out, named in the series' note, and another set is taken; a
series still short after ``2 n`` sets is returned with what it has (the campaign stores
it with a ``short-series`` event). A series whose first :data:`GIVE_UP_SETS` sets all
miss is a :class:`~cellcal.errors.NoTargetError` (the campaign keeps the pose with the
other sensors). A camera that gives nothing after its own retries is named in the note,
and the set is measured with the others; a set with no frame at all is a device fault.
A complete series' note becomes a ``sensor-note`` event of the campaign.

A sample's host time is the clock when its set was triggered. Whoever listens to the
rig's sets (:data:`SetListener`, set on the options: mock mode's camera twin) is told
each set's index in its series and that time before the cameras are triggered.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, PlainValidator, PrivateAttr, SerializeAsAny
from pydantic_core import PydanticCustomError

from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.calib.photogrammetry.rig_measurement import TargetMeter, mean_of
from cellcal.calib.photogrammetry.target_pose import TargetPose
from cellcal.calib.rotations import quaternion_from_matrix
from cellcal.clock import Clock
from cellcal.device_options import SensorOptions
from cellcal.drivers.base import DeviceContext, DeviceDescription, Series, naming_errors
from cellcal.drivers.cameras.backends import CameraRig, FrameSet, RigOptions, rig_class
from cellcal.errors import DeviceError, MeasurementError, NoTargetError, UserError
from cellcal.families import camera_backend, camera_backends, load
from cellcal.files.images import write_image
from cellcal.files.photogrammetry import read_rig, read_target

#: A series whose first sets all miss the target stops after this many.
GIVE_UP_SETS = 3

#: Told of each set before its cameras are triggered: its index in the series (0, 1, …;
#: a series measured again at the same pose starts at 0 again) and the clock's time.
SetListener = Callable[[int, float], None]


def _capture(value: Any) -> RigOptions:
    """``[sensor.capture]``: the rig options of the backend it names, a row of the
    registry's camera backends (``cellcal/families.py``) that a configuration may name
    (not a mock-only one); its model imported when a file names it."""
    if isinstance(value, RigOptions):
        return value
    if not isinstance(value, dict):
        raise PydanticCustomError("capture", "expected a table")
    choices = ", ".join(b.name for b in camera_backends(configurable=True))
    backend = value.get("backend")
    row = camera_backend(backend) if isinstance(backend, str) else None
    if backend is None:
        raise PydanticCustomError("capture", f"backend: required key missing (choose {choices})")
    if row is None or row.mock_only:
        raise PydanticCustomError(
            "capture", f"backend: {backend!r} is not a camera backend (choose {choices})"
        )
    out: RigOptions = load(row.options, libraries=False).model_validate(value)
    return out


#: What ``[sensor.capture]`` may be: a backend's rig options, told apart by ``backend``
#: (the backends are the registry's rows: :func:`_capture`).
CaptureOptions = Annotated[SerializeAsAny[RigOptions], PlainValidator(_capture)]


def _mock_only(backend: str) -> bool:
    """A backend no configuration names (mock mode's in-process cameras): its cameras
    are nowhere."""
    row = camera_backend(backend)
    return row is not None and row.mock_only


class CameraRigOptions(SensorOptions):
    """A photogrammetry rig of cameras: ``rig_file`` (its calibration), ``target_file``
    (the marker fixture on the flange), ``capture`` (the cameras), ``min_cameras`` (a
    set needs the target in this many), ``keep_images`` (a folder: each set's images are
    kept there for audit, ``<sensor>/<host time ms>/<camera>.png``; empty: not kept)."""

    kind: Literal["photogrammetry"] = "photogrammetry"
    driver: Literal["cameras"] = "cameras"
    rig_file: Annotated[str, Field(min_length=1)]
    target_file: Annotated[str, Field(min_length=1)]
    capture: CaptureOptions
    min_cameras: Annotated[int, Field(ge=2, le=64)] = 2
    keep_images: str = ""
    # not configurable: mock mode's camera twin listens to the sets (module docstring)
    _set_listener: SetListener | None = PrivateAttr(default=None)

    @property
    def set_listener(self) -> SetListener | None:
        return self._set_listener

    def listened(self, listener: SetListener) -> CameraRigOptions:
        """These options with ``listener`` told of every set the sensor triggers."""
        out = self.model_copy()
        out._set_listener = listener
        return out

    def endpoint(self) -> str:
        """The cameras' addresses (a recording's folder for ``files``)."""
        return self.capture.endpoint()

    def relative_to(self, folder: Path) -> CameraRigOptions:
        """Relative file paths taken relative to the configuration's folder."""

        def at(path: str) -> str:
            return path if not path or Path(path).is_absolute() else str(folder / path)

        capture = self.capture.relative_to(folder)
        return self.model_copy(
            update={
                "rig_file": at(self.rig_file),
                "target_file": at(self.target_file),
                "keep_images": at(self.keep_images),
                "capture": capture,
            }
        )

    def named_files(self) -> dict[str, str]:
        return {"rig_file": self.rig_file, "target_file": self.target_file}


def rig_and_target(options: CameraRigOptions) -> tuple[Rig, Target]:
    """The configured rig and target files, read; one line naming the sensor if not."""
    try:
        return read_rig(options.rig_file), read_target(options.target_file)
    except UserError as exc:
        raise DeviceError(f"sensor {options.name}: {exc}", device=options.name) from None


class CameraRigSensor:
    """A :class:`~cellcal.drivers.base.PositionSensor` made of a camera rig, its
    calibration and the target it measures; ``address``: its cameras' (the configured
    endpoint). Every DeviceError of its calls names it (``device``: its name), the
    cameras' too."""

    def __init__(
        self,
        name: str,
        cameras: CameraRig,
        rig: Rig,
        target: Target,
        clock: Clock,
        *,
        min_cameras: int = 2,
        keep_images: str = "",
        set_listener: SetListener | None = None,
        address: str = "",
    ) -> None:
        missing = sorted({c.name for c in rig.cameras} - set(cameras.cameras))
        extra = sorted(set(cameras.cameras) - {c.name for c in rig.cameras})
        if missing or extra:
            raise DeviceError(
                f"{name}: the capture's cameras {list(cameras.cameras)} are not the rig "
                f"file's {[c.name for c in rig.cameras]} (missing {missing}, unknown {extra})",
                device=name,
            )
        self.name = name
        self.address = address
        self.cameras = cameras
        self.rig = rig
        self.target = target
        self.clock = clock
        self.meter = TargetMeter(rig, target, min_cameras=min_cameras)
        self.keep_images = Path(keep_images) if keep_images else None
        self.set_listener = set_listener
        self._grabber = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{name}-grab")

    @classmethod
    def from_options(cls, options: CameraRigOptions, context: DeviceContext) -> CameraRigSensor:
        rig, target = rig_and_target(options)
        # also mock mode's in-process cameras (backend "rendered"), which are nowhere
        backend: str = options.capture.backend
        cameras = rig_class(backend).from_options(options.capture, clock=context.clock)
        return cls(
            options.name,
            cameras,
            rig,
            target,
            context.clock,
            min_cameras=options.min_cameras,
            keep_images=options.keep_images,
            set_listener=options.set_listener,
            address="" if _mock_only(backend) else options.endpoint(),
        )

    @naming_errors
    def connect(self) -> None:
        self.cameras.connect()

    def close(self) -> None:
        self._grabber.shutdown(wait=True)
        self.cameras.close()

    @naming_errors
    def describe(self) -> DeviceDescription:
        """The rig at its cameras' addresses, each camera as it says of itself
        (``parts``); a rig tells nothing of itself as a whole."""
        parts = self.cameras.describe()
        family = "photogrammetry/cameras"
        return DeviceDescription(self.name, family, self.address or None, parts=parts)

    @naming_errors
    def measure(self, n: int, rate_hz: float) -> Series:
        """``n`` samples at ``rate_hz``: the reference point of each set that measured,
        sets taken until ``n`` measured or ``2 n`` were taken (module docstring). The
        next set is grabbed while this one is measured when it is sure to be needed."""
        self.meter.reset()
        t0 = self.clock.now()
        poses: list[TargetPose] = []
        host: list[float] = []
        device: list[float] = []
        missed: list[str] = []
        lost: list[str] = []
        retries = 0
        k = 0  # sets taken so far
        pending: Future[tuple[float, FrameSet]] | None = self._trigger(t0, k)
        try:
            while pending is not None:
                when, frames = pending.result()
                k += 1
                pending = None
                if len(poses) + 1 < n and k < 2 * n:  # needed whether this set measures
                    pending = self._trigger(t0 + k / rate_hz, k)
                retries += frames.retries
                if not frames.frames:
                    reasons = "; ".join(f"{c}: {why}" for c, why in frames.lost.items())
                    raise DeviceError(f"{self.name}: no camera gave a frame ({reasons})")
                for cam, why in frames.lost.items():
                    lost.append(f"set {k - 1}: camera {cam} lost ({why})")
                self._keep(when, frames)
                try:
                    images = {c: f.image for c, f in frames.frames.items()}
                    poses.append(self.meter.measure(images))
                except MeasurementError as exc:
                    missed.append(f"set {k - 1}: {exc}")
                    if not poses and k >= GIVE_UP_SETS:
                        break  # the robot holds still: the next sets would not see it either
                    if pending is None and k < 2 * n:
                        pending = self._trigger(t0 + k / rate_hz, k)
                    continue
                host.append(when)
                device.append(next(iter(frames.frames.values())).device_time)
        finally:
            if pending is not None:
                wait([pending])
        if not poses:
            raise NoTargetError(f"{self.name}: no set measured the target ({missed[0]})")
        mean = mean_of(poses)
        return Series(
            self.name,
            np.array(host),
            np.array(device),
            np.array([p.xyz_mm for p in poses]),
            retries=retries,
            cov=np.array([p.cov_mm2 for p in poses]),
            orientation=quaternion_from_matrix(np.array([p.T_rig_target[:3, :3] for p in poses])),
            mean_cov=mean.cov_mm2,
            note=_summary(len(poses), n, k, missed, lost),
        )

    def _trigger(self, when: float, index: int) -> Future[tuple[float, FrameSet]]:
        """Wait on the clock until ``when``, then grab set ``index`` of the series in the
        background (on a branch of the clock from ``when``: its frames are stamped in
        this series' time); the future gives the clock at the trigger and the set."""
        wait_s = when - self.clock.now()
        if wait_s > 0:
            self.clock.sleep(wait_s)
        listener = self.set_listener

        def grab() -> tuple[float, FrameSet]:
            with self.clock.branch(when):
                t = self.clock.now()
                if listener is not None:
                    listener(index, t)
                return t, self.cameras.grab()

        return self._grabber.submit(grab)

    def _keep(self, t: float, frames: FrameSet) -> None:
        if self.keep_images is None:
            return
        folder = self.keep_images / self.name / f"{round(t * 1000):013d}"
        folder.mkdir(parents=True, exist_ok=True)
        for cam, f in frames.frames.items():
            write_image(folder / f"{cam}.png", f.image)


def _summary(measured: int, n: int, taken: int, missed: list[str], lost: list[str]) -> str:
    """The series' note: how many of ``n`` samples it has after how many sets, what
    went wrong on the way and the first reasons; empty when nothing did."""
    if not missed and not lost:
        return ""
    counts = []
    if missed:
        counts.append(f"{len(missed)} set{'s' * (len(missed) != 1)} missed the target")
    if lost:
        counts.append(f"{len(lost)} camera frame{'s' * (len(lost) != 1)} lost")
    notes = sorted(missed + lost, key=lambda s: int(s.split(":", 1)[0].removeprefix("set ")))
    shown = "; ".join(notes[:3]) + ("; …" if len(notes) > 3 else "")
    return f"{measured} of {n} samples after {taken} sets ({', '.join(counts)}): {shown}"
