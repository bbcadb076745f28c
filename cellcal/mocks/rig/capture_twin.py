"""The camera twins ``cellcal rig capture --mock`` grabs from: the simulated cell's
cameras, reached through the configured driver as in a campaign, showing the flange's
target where the simulated robot holds it, or a ChArUco board held up at a new pose for
every set (:class:`~cellcal.mocks.rig.board_views.BoardScene`).

Where the configured backend's row of the registry (``CAMERA_BACKENDS`` in
``cellcal/families.py``) has a twin that can run here — ``aravis``: GigE Vision cameras,
in a network namespace — the board's views are served by it and the configured driver
grabs them; otherwise the frames are rendered in-process and a warning says why (as
``cellcal run --mock`` does).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellcal.clock import WallClock
from cellcal.config import CellConfig
from cellcal.drivers.cameras.backends import Frame, FrameSet, rig_class
from cellcal.drivers.photogrammetry import CameraRigOptions, rig_and_target
from cellcal.families import camera_backend, load
from cellcal.mocks.rig.board_views import BoardScene

log = logging.getLogger(__name__)


class SceneRig:
    """A rig whose frames a scene renders in-process (no camera protocol)."""

    def __init__(self, scene: BoardScene, cameras: tuple[str, ...]) -> None:
        self.scene = scene
        self.cameras = cameras
        self.clock = WallClock()
        self._frame_id = 0

    def connect(self) -> None:
        self._frame_id = 0

    def grab(self) -> FrameSet:
        self._frame_id += 1
        t = self.clock.now()
        frames = {
            c: Frame(c, self.scene.image(c), self._frame_id, t, self.scene.device_time())
            for c in self.cameras
        }
        return FrameSet(frames, {})

    def close(self) -> None:
        self._frame_id = 0


@dataclass(frozen=True)
class MockRig:
    """The configured rig's driver pointed at the twins (``cameras``), how to stop them,
    and what to tell them before each set (its index, from 0)."""

    cameras: Any
    stop: Callable[[], None]
    announce: Callable[[int], None]


def _nothing(*args: Any) -> None:
    return None


def mock_rig(
    config: CellConfig,
    options: CameraRigOptions,
    board_path: str | None,
    n_sets: int,
    seed: int | None,
) -> MockRig:
    """The configured rig's driver pointed at the simulated cell's cameras."""
    from cellcal.files.models import load_model
    from cellcal.files.photogrammetry import read_board
    from cellcal.mocks.rig.twin import RigTruth, why_no_twin
    from cellcal.mocks.rig.twin import serve as serve_target
    from cellcal.mocks.simulated_cell import SimulatedCell

    cell = SimulatedCell(config, load_model(config.robot.model).model, seed)
    if board_path is None:
        twin = serve_target(options, cell, 0.0)
        capture = twin.options.capture
        return MockRig(rig_class(capture.backend).from_options(capture), twin.stop, _nothing)
    board = read_board(board_path)
    rig, _ = rig_and_target(options)
    truth = RigTruth.of(cell, options.name)
    scene = BoardScene(rig, board, n_sets, truth.seed, truth.blur_px, truth.noise_grey)
    names = options.capture.camera_names()
    backend = camera_backend(options.capture.backend)
    why = why_no_twin(options.capture.backend)
    if why is None:
        from cellcal.mocks.netns import NamespaceUnavailableError

        assert backend is not None and backend.twin is not None
        try:
            running = load(backend.twin)(options, scene)
        except NamespaceUnavailableError as exc:
            why = str(exc)
        else:
            capture = running.options
            cameras = rig_class(capture.backend).from_options(capture)
            return MockRig(cameras, running.stop, scene.announce)
    log.warning("sensor %s: cameras simulated in-process (%s)", options.name, why)
    return MockRig(SceneRig(scene, names), _nothing, scene.announce)
