"""The rig's twin: it follows the simulated robot, gives the same frames for the same
seed, and its process of its own ends with the campaign's, however that ends."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.commands.mock import simulated_cell_of
from cellcal.drivers.photogrammetry import rig_and_target
from cellcal.mocks.netns import NamespaceUnavailableError
from cellcal.mocks.rig.twin import DEVICE_CLOCK_S, RigScene, RigTruth, SetMarks

pytestmark = [pytest.mark.twin, pytest.mark.timeout(120)]


def _rig_sensor(config):
    return next(s for s in config.sensor if s.kind == "photogrammetry")


def test_a_watcher_follows_every_move_until_it_stops_watching():
    _, cell = simulated_cell_of(None, 7)
    seen = []
    stop = cell.watch(seen.append)
    assert len(seen) == 1 and np.array_equal(seen[0], cell.q)  # told where it is now
    q = cell.q + 0.1
    cell.set_q(q)
    assert np.array_equal(seen[-1], q)
    stop()
    cell.set_q(q + 0.1)
    assert len(seen) == 2


def test_the_same_seed_gives_the_same_frames_and_a_resume_fresh_noise():
    config, cell = simulated_cell_of(None, 11)
    sensor = _rig_sensor(config)
    rig, target = rig_and_target(sensor)

    def frames(noise_stream: int) -> list[np.ndarray]:
        truth = RigTruth.of(cell, sensor.name)
        truth = RigTruth(**{**truth.__dict__, "noise_stream": noise_stream})
        scene = RigScene(truth, rig, target, lambda: cell.q)
        return [scene.image(c.name) for c in rig.cameras for _ in range(2)]

    a, b, resumed = frames(0), frames(0), frames(3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], a[1])  # fresh noise per frame
    assert not any(np.array_equal(x, y) for x, y in zip(a, resumed, strict=True))
    # the target is in the middle of every camera's view, not plain background
    assert all(f.max() > 150 for f in a)


def test_a_frame_s_noise_is_its_set_s_whatever_came_before():
    """Announced sets: a camera's frame for set k at a pose is the same however many
    frames were taken before it (retries, lost frames, sets of another series), another
    set's or another arrival's differs; the cameras' clock reads the set's trigger."""
    config, cell = simulated_cell_of(None, 11)
    sensor = _rig_sensor(config)
    rig, target = rig_and_target(sensor)
    truth = RigTruth.of(cell, sensor.name)
    marks = SetMarks()
    announce = marks.listener(cell)
    scene = RigScene(truth, rig, target, lambda: cell.q, mark=marks.read)
    cam = rig.cameras[1].name

    announce(3, 7.3)
    first = scene.image(cam)
    assert scene.device_time() == 7.3 + DEVICE_CLOCK_S
    retried = scene.image(cam)  # the same set's trigger again
    announce(4, 7.4)
    other = scene.image(cam)
    announce(3, 9.3)  # set 3 of the series measured again at this pose
    again = scene.image(cam)
    assert np.array_equal(first, retried) and np.array_equal(first, again)
    assert not np.array_equal(first, other)
    home = cell.q
    cell.set_q(home + 0.01)
    cell.set_q(home)  # back: another arrival
    announce(3, 11.3)
    assert not np.array_equal(first, scene.image(cam))
    fresh = RigScene(truth, rig, target, lambda: cell.q, mark=marks.read)
    assert np.array_equal(fresh.image(cam), scene.image(cam))  # by the set, not the order


def test_the_camera_process_ends_when_the_campaign_is_gone():
    """The campaign's end of the pipe closes (as when it is killed): the cameras'
    process stops serving and exits by itself."""
    from cellcal.mocks.rig.process import serve_in_process

    config, cell = simulated_cell_of(None, 3)
    sensor = _rig_sensor(config)
    try:
        running = serve_in_process(sensor, RigTruth.of(cell, sensor.name), cell)
    except NamespaceUnavailableError as exc:
        pytest.skip(str(exc))
    child = running.server
    assert child.process.is_alive()
    assert running.options.netns.startswith(f"/proc/{child.process.pid}/")
    child.pipe.close()  # no "stop": the parent is simply gone
    deadline = time.monotonic() + 30.0
    while child.process.is_alive() and time.monotonic() < deadline:
        child.process.join(0.2)
    assert not child.process.is_alive() and child.process.exitcode == 0
    child.unwatch()
