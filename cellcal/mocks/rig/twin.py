"""The simulated cell's camera rig: what each camera sees of the flange's marker fixture.

At every trigger the twin renders the target where the simulated robot really holds it:
``T_rig_target = T_rig_base · T_base_flange(q, true geometry) · T_flange_target``, through
each camera's model in the rig file (``camera_render.py``: supersampled, blurred), one
clean image per camera per robot pose, fresh sensor noise per frame. The fixture is
mounted with its reference point at the sensor's true target offset and its face turned
toward the rig at the home orientation.

A frame's noise is a function of the seed, the noise stream, the camera, where the
robot is (the joints and how often it arrived there) and the set: the rig's sensor
tells the twin each set's index in its series and its trigger time before triggering
(:class:`SetMark`), so a frame grabbed again (an incomplete frame, a timeout), a camera
lost in one set or a series measured again at the same pose change no other set's
noise, and the same seed gives the same images whatever the load. The cameras' clocks
read the set's trigger time plus :data:`DEVICE_CLOCK_S`. Frames no sensor announced
(the driver's first grab, ``cellcal mock cameras``) take fresh noise in turn.

Mock mode serves those frames as GigE Vision cameras (``gige_cameras.py``, in a network
namespace of their own) and the configured ``aravis`` driver grabs them unchanged. Where
no namespace can be made (no root, no user namespaces), or for the ``opencv`` and
``files`` backends, it says so in one line and hands the rendered frames to the same
measuring code in-process (:class:`RenderedRig`).
"""

from __future__ import annotations

import itertools
import logging
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import cv2
import numpy as np

from cellcal.calib.geometry import Array, invert
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.calib.robot_model import RobotModel
from cellcal.clock import Clock, WallClock
from cellcal.device_options import Strict
from cellcal.drivers.base import DeviceDescription
from cellcal.drivers.cameras.aravis import AravisRigOptions
from cellcal.drivers.cameras.backends import Frame, FrameSet
from cellcal.drivers.photogrammetry import CameraRigOptions, rig_and_target
from cellcal.errors import DeviceError
from cellcal.families import camera_backend, load
from cellcal.mocks.rig.camera_render import (
    Image,
    Optics,
    Region,
    SceneRenderer,
    exposed,
    render_region,
)
from cellcal.mocks.rig.gige_cameras import fit
from cellcal.mocks.rig.sensor_noise import gaussian_noise
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.twins import RunningTwin

log = logging.getLogger("cellcal.mocks.rig")

#: Frames of plain background with noise drawn ahead per camera: a frame is one of them
#: with the target's window (fresh noise on every frame) written in.
NOISE_BANK = 8
#: How long mock mode waits for one camera's frame, s (rendering it takes time).
MOCK_TIMEOUT_S = 5.0
#: Sub-pixel samples per pixel side in the campaign's renders, as in the benchmark: 4
#: costs a quarter but leaves 0.02 mm of systematic error per pose mean, not 0.01.
SUPERSAMPLE = 8
#: The twin's cameras' clocks: the engine's clock at the set's trigger plus this, s.
DEVICE_CLOCK_S = 500.0


#: a camera's clean view of the target (the part of its image that is not plain
#: background, and where that part is) and its noisy frames of the plain background
_View = tuple[Image, Region, list[Image]]


def facing(toward: Array) -> Array:
    """A rotation whose z axis points along ``toward`` (x as level as it can be)."""
    z = toward / np.linalg.norm(toward)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


@dataclass(frozen=True, eq=False)
class RigTruth:
    """What the rig's twin needs of the simulated cell (picklable: a twin in a process of
    its own gets it): the true robot, where the rig truly is, the target's true offset
    on the flange, the imaging conditions and the seeds of the noise."""

    model: RobotModel
    T_rig_base: Array
    target_offset: Array
    home_deg: tuple[float, ...]
    cube_centre_mm: tuple[float, ...]
    blur_px: float
    noise_grey: float
    seed: int
    noise_stream: int

    @classmethod
    def of(cls, cell: SimulatedCell, sensor: str) -> RigTruth:
        truth = cell.sensors[sensor]
        sim = cell.simulation
        return cls(
            cell.model.with_terms(cell.terms),  # the payload-free load: rendered at start
            truth.T_sensor_base,
            truth.target_offset,
            tuple(cell.home_deg),
            tuple(cell.cube_centre_mm),
            sim.rig_blur_px,
            sim.rig_noise_grey,
            cell.seed,
            cell.noise_stream,
        )


@dataclass(frozen=True)
class SetMark:
    """The set the rig's sensor announced last: where the robot was (``pose``, a checksum
    of the joints, and ``visit``, its arrivals there: the simulated cell's
    :attr:`~cellcal.mocks.simulated_cell.SimulatedCell.pose_key`), the set's index in
    its series and the engine's clock at its trigger (s)."""

    pose: int
    visit: int
    index: int
    time: float


def pose_checksum(q: Array) -> int:
    """The checksum of joint positions that a :class:`SetMark`'s ``pose`` holds."""
    return zlib.crc32(np.asarray(q, dtype=np.float64).tobytes())


class SetMarks:
    """The last set announced, in this process: ``listener(cell)`` is what the rig's
    sensor calls (its options' set listener), ``last`` what the scene reads."""

    def __init__(self) -> None:
        self.last: SetMark | None = None

    def listener(self, cell: SimulatedCell) -> Callable[[int, float], None]:
        def announce(index: int, t: float) -> None:
            pose, visit = cell.pose_key
            self.last = SetMark(pose, visit, index, t)

        return announce

    def read(self) -> SetMark | None:
        return self.last


class RigScene:
    """The rig's view of the simulated cell: ``image(camera)`` is that camera's frame
    now, with the robot at ``joints()`` (rad), for the set ``mark()`` says (None, or no
    ``mark``: frames no sensor announced). Thread-safe: the cameras are triggered
    together from their own threads."""

    def __init__(
        self,
        truth: RigTruth,
        rig: Rig,
        target: Target,
        joints: Callable[[], Array],
        optics: Optics | None = None,
        mark: Callable[[], SetMark | None] | None = None,
    ) -> None:
        self.truth = truth
        self.joints = joints
        self.mark = mark
        self.rig = rig
        optics = optics or Optics(
            supersample=SUPERSAMPLE, blur_px=truth.blur_px, noise_grey=truth.noise_grey
        )
        self.renderer = SceneRenderer.for_target(rig.cameras, target, optics)
        self.T_rig_base = truth.T_rig_base
        # the fixture faces the rig's cameras when the flange is at home
        home = np.radians(np.asarray(truth.home_deg, dtype=np.float64))
        R0 = target_kinematics(truth.model, home[None], np.zeros(3), jacobian=False).R_flange[0]
        eyes = np.array([c.T_rig_cam[:3, 3] for c in rig.cameras]).mean(axis=0)
        T_base_rig = invert(self.T_rig_base)
        toward = T_base_rig[:3, :3] @ eyes + T_base_rig[:3, 3] - np.asarray(truth.cube_centre_mm)
        R = R0.T @ facing(toward)
        self.T_flange_target = np.eye(4)
        self.T_flange_target[:3, :3] = R
        self.T_flange_target[:3, 3] = truth.target_offset - R @ target.reference
        self._lock = threading.Lock()
        self._rendering = threading.Lock()
        self._q: Array | None = None
        self._pose = 0
        self._T = np.eye(4)
        self._clean: dict[str, _View] = {}
        # the noise is seeded per frame (the module's note); a resumed campaign, the
        # cell's next noise stream, draws fresh noise
        self._camera_k = {c.name: k for k, c in enumerate(rig.cameras)}
        self._unannounced = dict.fromkeys(self._camera_k, 0)
        self._bank = _NoiseBank(truth, rig, optics)

    def T_rig_target(self, q: Array) -> Array:
        k = target_kinematics(self.truth.model, q[None], np.zeros(3), jacobian=False)
        T_base_flange = np.eye(4)
        T_base_flange[:3, :3] = k.R_flange[0]
        T_base_flange[:3, 3] = k.p[0]
        out: Array = self.T_rig_base @ T_base_flange @ self.T_flange_target
        return out

    def image(self, camera: str) -> Image:
        """Camera ``camera``'s frame of the target where the robot holds it now. Each
        camera renders its own view once per robot pose, on its own thread."""
        c = self.rig.camera(camera)
        frame = np.empty((c.height, c.width), dtype=np.uint8)
        self.write(camera, frame)
        return frame

    def write(self, camera: str, out: Image) -> None:
        """:meth:`image` written into ``out`` (the camera's own frame buffer: no image
        is allocated per frame); another size or pixel type is cropped, padded or
        scaled as :func:`~cellcal.mocks.rig.gige_cameras.fit` does."""
        q = self.joints()
        mark = self.mark() if self.mark is not None else None
        with self._lock:
            if self._q is None or not np.array_equal(q, self._q):
                self._q, self._T = q, self.T_rig_target(q)
                self._pose = pose_checksum(q)
                self._clean.clear()
            T = self._T
            cached = self._clean.get(camera)
            if mark is not None and mark.pose == self._pose:
                key = [self._pose, mark.visit, 1, mark.index]
            else:
                key = [self._pose, 0, 0, self._unannounced[camera]]
                self._unannounced[camera] += 1
        if cached is None:
            # one render at a time: the cameras' threads are triggered together, and
            # four renders taking turns under the interpreter lock all end late
            with self._rendering:
                cached = self._render(camera, T)
            with self._lock:
                if self._q is not None and np.array_equal(q, self._q):
                    self._clean[camera] = cached
        part, (rows, cols), bank = cached
        truth = self.truth
        rng = np.random.default_rng(
            [truth.seed, 2, truth.noise_stream, self._camera_k[camera], *key]
        )
        k = int(rng.integers(len(bank)))
        noise = None
        if rows.stop > rows.start and cols.stop > cols.start:
            shape = (rows.stop - rows.start, cols.stop - cols.start)
            noise = gaussian_noise(shape, rng, self.renderer.optics.noise_grey)
        if out.dtype == np.uint8 and out.shape == bank[k].shape:
            np.copyto(out, bank[k])  # the camera's own buffer: written in place
            frame = out
        else:
            frame = bank[k].copy()
        if noise is not None:
            frame[rows, cols] = cv2.add(part, noise, dtype=cv2.CV_8U)
        if frame is not out:
            np.copyto(out, fit(frame, out.shape[0], out.shape[1], out.dtype))

    def device_time(self) -> float:
        """The cameras' clock (s): the announced set's trigger time plus
        :data:`DEVICE_CLOCK_S` (its offset alone before any set)."""
        mark = self.mark() if self.mark is not None else None
        return (mark.time if mark is not None else 0.0) + DEVICE_CLOCK_S

    def _render(self, camera: str, T_rig_target: Array) -> _View:
        """One camera's clean view of the target and its bank of noisy frames of the
        plain background."""
        cam = self.rig.camera(camera)
        part, region = render_region(cam, self.renderer.faces, T_rig_target, self.renderer.optics)
        return part, region, self._bank.frames(camera)


class _NoiseBank:
    """Each camera's :data:`NOISE_BANK` frames of plain background with noise, drawn
    from the camera's own seed by a thread per camera as the scene is made (about 0.1 s
    a camera: the cameras open meanwhile); a camera's first frame waits for them."""

    def __init__(self, truth: RigTruth, rig: Rig, optics: Optics) -> None:
        self._frames: dict[str, list[Image]] = {}
        self._failed: dict[str, BaseException] = {}
        self._ready: dict[str, threading.Event] = {}
        for k, c in enumerate(rig.cameras):
            self._ready[c.name] = threading.Event()
            seed = [truth.seed, 2, truth.noise_stream, k]
            args = (c.name, (c.height, c.width), seed, optics)
            threading.Thread(target=self._draw, args=args, name="rig-noise", daemon=True).start()

    def _draw(self, name: str, shape: tuple[int, int], seed: list[int], optics: Optics) -> None:
        try:
            background = np.full(shape, optics.background, dtype=np.float32)
            rng = np.random.default_rng(seed)
            self._frames[name] = [
                exposed(background, rng, optics.noise_grey) for _ in range(NOISE_BANK)
            ]
        except BaseException as exc:  # the camera's first frame raises it
            self._failed[name] = exc
        finally:
            self._ready[name].set()

    def frames(self, name: str) -> list[Image]:
        self._ready[name].wait()
        if name in self._failed:
            raise DeviceError(f"camera {name}: noise bank: {self._failed[name]}")
        return self._frames[name]


class RenderedRigOptions(Strict):
    """Mock mode's in-process rig: the scene's rendered frames, no camera protocol."""

    name: str = "rig"
    backend: Literal["rendered"] = "rendered"
    cameras: tuple[str, ...]
    scene: int


#: live scenes by id (the options of an in-process rig name theirs)
_SCENES: dict[int, RigScene] = {}
_ids = itertools.count(1)


class RenderedRig:
    """A :class:`~cellcal.drivers.cameras.backends.CameraRig` that renders its frames in-process."""

    def __init__(self, options: RenderedRigOptions, clock: Clock | None = None) -> None:
        scene = _SCENES.get(options.scene)
        if scene is None:
            raise DeviceError(f"rig {options.name}: its simulated scene is gone")
        self.name = options.name
        self.cameras = options.cameras
        self.scene = scene
        self.clock = clock or WallClock()
        self._frame_id = 0

    @classmethod
    def from_options(cls, options: RenderedRigOptions, clock: Clock | None = None) -> RenderedRig:
        return cls(options, clock)

    def connect(self) -> None:
        self._frame_id = 0

    def grab(self) -> FrameSet:
        self._frame_id += 1
        t = self.clock.now()
        frames = {
            c: Frame(c, self.scene.image(c), self._frame_id, t, t + DEVICE_CLOCK_S)
            for c in self.cameras
        }
        return FrameSet(frames, {})

    def describe(self) -> tuple[DeviceDescription, ...]:
        """Each camera's name: rendered in-process, no address, nothing to identify."""
        return tuple(DeviceDescription(c, "rendered") for c in self.cameras)

    def close(self) -> None:
        self._frame_id = 0


@dataclass
class RigTwin:
    """A running twin of a configured rig: ``options`` point the driver at it."""

    options: CameraRigOptions
    server: Any = None
    scene_id: int | None = None

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.scene_id is not None:
            _SCENES.pop(self.scene_id, None)


def serve(options: CameraRigOptions, cell: SimulatedCell, time_scale: float) -> RigTwin:
    """The simulated cell's cameras for the configured rig: served by the twin of the
    capture backend's row in a process of their own (for ``aravis``: GigE Vision cameras
    in a network namespace) when the row has a twin that can run here, else rendered
    in-process."""
    rig, target = rig_and_target(options)
    truth = RigTruth.of(cell, options.name)
    capture = options.capture
    why = why_no_twin(capture.backend)
    if why is None:
        from cellcal.mocks.netns import NamespaceUnavailableError
        from cellcal.mocks.rig.process import CameraProcess, serve_in_process

        try:
            running = serve_in_process(options, truth, cell)
        except NamespaceUnavailableError as exc:
            why = str(exc)
        else:
            assert isinstance(running.server, CameraProcess)
            pointed = options.model_copy(update={"capture": running.options})
            return RigTwin(pointed.listened(running.server.announce), running)
    log.warning("sensor %s: cameras simulated in-process (%s)", options.name, why)
    sid = next(_ids)
    marks = SetMarks()
    _SCENES[sid] = RigScene(truth, rig, target, lambda: cell.q, mark=marks.read)
    names = capture.camera_names()
    rendered = RenderedRigOptions(name=capture.name, cameras=names, scene=sid)
    pointed = options.model_copy(update={"capture": rendered})
    return RigTwin(pointed.listened(marks.listener(cell)), None, sid)


class CameraScene(Protocol):
    """What GigE Vision camera twins serve: a rig's cameras, each camera's next frame
    (or written into its buffer) and the cameras' clock (s)."""

    rig: Rig

    def image(self, camera: str) -> Image: ...

    def write(self, camera: str, out: Image) -> None: ...

    def device_time(self) -> float: ...


def serve_gige(options: CameraRigOptions, scene: CameraScene) -> RunningTwin:
    """The scene's cameras as GigE Vision devices for the rig's ``aravis`` capture (in a
    network namespace of this process), the options pointed at them."""
    from cellcal.mocks.rig.gige_cameras import serve_rig

    capture = options.capture
    assert isinstance(capture, AravisRigOptions)
    cam = scene.rig.cameras[0]
    # a camera's first frame at a new robot pose is rendered (0.05-0.5 s on a busy
    # machine), which a real camera does not need: mock mode waits longer for it
    slow = [
        c.model_copy(update={"timeout_s": max(c.timeout_s, MOCK_TIMEOUT_S)})
        for c in capture.cameras
    ]
    capture = capture.model_copy(update={"cameras": slow})
    return serve_rig(
        capture,
        scene.image,
        width=cam.width,
        height=cam.height,
        writer=scene.write,
        device_clock=scene.device_time,
    )


def why_no_twin(backend: str) -> str | None:
    """Why the cameras of the capture's backend cannot be served by its twin here (the
    registry's row: no twin, or its ``unavailable`` says why), or None."""
    row = camera_backend(backend)
    if row is None or row.twin is None:
        return f'backend "{backend}" has no protocol twin'
    return load(row.unavailable)() if row.unavailable is not None else None
