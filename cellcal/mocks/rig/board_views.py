"""The simulated cell's cameras looking at a ChArUco board held up in front of the rig,
for ``rig calibrate`` to be tried without a real board: ``cellcal mock cameras --board``
and ``cellcal rig capture --mock --board``.

The board takes ``views`` poses in turn (:func:`~cellcal.mocks.rig.scene.board_poses`:
facing the rig, tilted up to ±35° on a spiral, turned and shifted about the volume the
cameras look at). A grabber that knows which set it takes says so (:meth:`announce`:
``rig capture --mock`` does) and set k shows pose k; a frame taken again shows the same
pose. For any other client (``cellcal mock cameras``) a set is a burst of frames: the
board moves on when a camera asks for a second frame at the same pose, or when
:data:`BURST_GAP_S` has passed since the last frame was asked for (the cameras of a set
are triggered within milliseconds of each other; the next set comes after a new pose is
rendered, a tenth of a second later), so a client's stray frames (a camera's first frame
after acquisition starts late) form a pose of their own and do not mix into a set.
A frame's noise is a function of the seed, the camera, the pose's turn and how many
frames that camera took at it, so the same seed gives the same images. Each view is
rendered once per camera when its first frame is asked for (the camera twin's renderer,
8×8 samples per pixel where the scene changes, the cell's blur and noise).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.calib.photogrammetry.camera_rig import Board, Rig
from cellcal.mocks.rig.camera_render import Image, Optics, SceneRenderer, exposed, render_region
from cellcal.mocks.rig.gige_cameras import fit
from cellcal.mocks.rig.scene import board_poses
from cellcal.mocks.rig.twin import SUPERSAMPLE

#: The stream of the seed the board views' noise is drawn from (the target's is 2).
NOISE_STREAM = 7
#: Frames asked for after this quiet time are a new set (s), unless one is announced.
BURST_GAP_S = 0.05


class BoardScene:
    """A board shown to ``rig``'s cameras at ``views`` poses in turn (thread-safe: the
    cameras are triggered together from their own threads)."""

    def __init__(
        self,
        rig: Rig,
        board: Board,
        views: int,
        seed: int,
        blur_px: float = 0.8,
        noise_grey: float = 2.0,
    ) -> None:
        if views < 1:
            raise ValueError(f"views: at least one, got {views}")
        self.rig = rig
        self.board = board
        self.seed = seed
        self.poses: list[Array] = board_poses(rig, board, views, seed=seed)
        optics = Optics(supersample=SUPERSAMPLE, blur_px=blur_px, noise_grey=noise_grey)
        self.renderer = SceneRenderer.for_board(rig.cameras, board, optics)
        self._lock = threading.Lock()
        self._turn = 0  # how many times the board has moved
        self._served: dict[str, int] = {}  # frames each camera took at this turn
        self._announced = False
        self._last = -float("inf")  # when the last frame was asked for (monotonic s)
        self._index = {c.name: k for k, c in enumerate(rig.cameras)}
        self._clean: dict[str, tuple[int, Image]] = {}

    def image(self, camera: str) -> Image:
        """The camera's next frame (8-bit): the board at its next pose."""
        with self._lock:
            now = time.monotonic()
            quiet = now - self._last > BURST_GAP_S
            self._last = now
            if not self._announced and self._served and (camera in self._served or quiet):
                self._turn += 1
                self._served.clear()
            taken = self._served.get(camera, 0)
            self._served[camera] = taken + 1
            n = self._turn
            cached = self._clean.get(camera)
        view = n % len(self.poses)
        if cached is None or cached[0] != view:
            cam = self.rig.camera(camera)
            part, region = render_region(
                cam, self.renderer.faces, self.poses[view], self.renderer.optics
            )
            clean: Image = np.full(
                (cam.height, cam.width), self.renderer.optics.background, dtype=np.float32
            )
            clean[region] = part
            with self._lock:
                self._clean[camera] = (view, clean)
            cached = (view, clean)
        rng = np.random.default_rng([self.seed, NOISE_STREAM, self._index[camera], n, taken])
        frame: Image = exposed(cached[1], rng, self.renderer.optics.noise_grey)
        return frame

    def announce(self, index: int) -> None:
        """The next frames are set ``index``'s (from 0): the board at pose ``index``."""
        with self._lock:
            self._announced = True
            if index != self._turn:
                self._turn = index
                self._served.clear()

    def write(self, camera: str, out: Image) -> None:
        """:meth:`image` written into the camera's own buffer ``out``."""
        np.copyto(out, fit(self.image(camera), out.shape[0], out.shape[1], out.dtype))

    def device_time(self) -> float:
        """The cameras' clock (s): the host's, as a camera with no campaign to follow."""
        return time.time()
