"""The camera rig as a campaign sensor, built by the device factory in mock mode: the
aravis driver against GigE Vision twins that render the simulated cell. Faults in the
measuring path: a camera that stops answering, a target out of view; and the in-process
fallback, the configuration's paths and keep_images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cellcal.config import load_config
from cellcal.drivers.cameras.backends import CameraOptions
from cellcal.drivers.cameras.files import FilesRigOptions
from cellcal.errors import MeasurementError, NoTargetError
from cellcal.families import find
from tests.drivers.families import cell_for, mock_devices

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(120)]

FAMILY = find("sensor", "photogrammetry", "cameras")
ROOT = Path(__file__).resolve().parents[2]


def _rig(devices):
    setting = next(s for s in devices.sensors if s.sensor.name == "rig")
    twin = next(t for t in devices.servers if type(t).__name__ == "RigTwin")
    return setting.sensor, twin


def _near_home(config, k=0):
    return np.radians(config.robot.home_deg) + np.radians([5.0 * k, -4.0, 3.0, 8.0, -5.0, 10.0])


def test_a_series_carries_covariances_orientations_and_the_truth():
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, twin = _rig(devices)
        assert type(twin.server).__name__ == "RunningTwin"  # GigE Vision, not in-process
        devices.robot.move_joints(_near_home(config), 0.25)
        s = sensor.measure(8, 10.0)
        assert s.n == 8 and s.cov.shape == (8, 3, 3) and s.orientation.shape == (8, 4)
        np.testing.assert_allclose(np.linalg.norm(s.orientation, axis=1), 1.0, atol=1e-12)
        sigma = np.sqrt(np.diagonal(s.cov, axis1=1, axis2=2))
        assert ((sigma > 0.002) & (sigma < 0.1)).all()
        # the mean's covariance holds the floor: not the samples' over n
        assert np.trace(s.mean_cov) > np.trace(s.cov.mean(axis=0)) / s.n
        truth = devices.simulated_cell.true_position("rig")
        err = s.mean - truth
        assert float(err @ np.linalg.solve(s.mean_cov, err)) < 25.0  # within 5σ
        assert np.linalg.norm(err) < 0.05
        assert s.note == ""


def test_a_camera_that_stops_mid_series_is_named_and_the_others_measure():
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, twin = _rig(devices)
        devices.robot.move_joints(_near_home(config, 1), 0.25)
        grab = sensor.cameras.grab
        calls = {"n": 0}

        def grab_then_stop():
            calls["n"] += 1
            if calls["n"] == 4:
                twin.server.server.stop_camera("cam3")
            return grab()

        sensor.cameras.grab = grab_then_stop
        s = sensor.measure(8, 10.0)
        assert s.n == 8  # three cameras still see the target
        # the trigger is retried by Aravis's control protocol, then the camera is named
        assert "camera cam3 lost" in s.note and "not acknowledged" in s.note
        truth = devices.simulated_cell.true_position("rig")
        assert np.linalg.norm(s.mean - truth) < 0.05


def _missing(sensor, misses):
    """The sensor's meter misses the target in the sets ``misses(k)`` says (k: the
    set's place in the series); the grabs are counted, the images kept."""
    measure, grab = sensor.meter.measure, sensor.cameras.grab
    seen = {"sets": 0, "grabs": 0, "images": []}

    def scripted(images):
        k = seen["sets"]
        seen["sets"] += 1
        seen["images"].append(images)
        if misses(k):
            raise MeasurementError(f"target 'dome' seen by 1 camera(s) (scripted {k})")
        return measure(images)

    def counting():
        seen["grabs"] += 1
        return grab()

    sensor.meter.measure, sensor.cameras.grab = scripted, counting
    return seen


def test_sets_that_miss_are_taken_again_until_n_measured():
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, _ = _rig(devices)
        devices.robot.move_joints(_near_home(config, 3), 0.25)
        measure, grab = sensor.meter.measure, sensor.cameras.grab
        plain = _missing(sensor, lambda k: False)
        full = sensor.measure(8, 10.0)
        sensor.meter.measure, sensor.cameras.grab = measure, grab
        seen = _missing(sensor, lambda k: k in (2, 5))
        t0 = sensor.clock.now()
        s = sensor.measure(6, 10.0)
    assert s.n == 6 and seen["grabs"] == 8 and full.n == 8
    assert s.note == (
        "6 of 6 samples after 8 sets (2 sets missed the target): set 2: target 'dome' seen "
        "by 1 camera(s) (scripted 2); set 5: target 'dome' seen by 1 camera(s) (scripted 5)"
    )
    kept = [0, 1, 3, 4, 6, 7]
    # a sample's host time is its set's trigger; the twin's cameras stamp it too
    np.testing.assert_allclose(s.host_time, t0 + 0.1 * np.array(kept), atol=1e-9)
    np.testing.assert_allclose(s.device_time, s.host_time + 500.0, atol=1e-6)
    # a set's images depend on its place in the series alone: the sets left out change
    # none of the others
    for a, b in zip(seen["images"], plain["images"], strict=True):
        assert a.keys() == b.keys() and all(np.array_equal(a[c], b[c]) for c in a)
    np.testing.assert_array_equal(s.xyz[:2], full.xyz[:2])


def test_a_series_short_after_twice_n_sets_keeps_what_it_has_and_says_why():
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, _ = _rig(devices)
        devices.robot.move_joints(_near_home(config, 4), 0.25)
        seen = _missing(sensor, lambda k: k % 3 != 0)
        s = sensor.measure(5, 10.0)
    assert s.n == 4 and seen["grabs"] == 10  # sets 0, 3, 6, 9 measured: 2 × 5 sets taken
    assert s.cov.shape == (4, 3, 3) and s.orientation.shape == (4, 4)
    assert s.note.startswith(
        "4 of 5 samples after 10 sets (6 sets missed the target): set 1: target 'dome' seen "
        "by 1 camera(s) (scripted 1); set 2: "
    )


def test_a_set_grabbed_again_or_measured_again_at_the_pose_has_the_same_images():
    """The twin keys each frame's noise on the pose and the set's place in the series: a
    trigger repeated for a set (as a retried frame is), or the series measured again at
    the same pose (the engine's re-ask), gives the same numbers; coming back to the pose
    later gives others."""
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, _ = _rig(devices)
        here, away = _near_home(config, 5), _near_home(config, 6)
        devices.robot.move_joints(here, 0.25)
        first = sensor.measure(4, 10.0)
        grab = sensor.cameras.grab

        def twice():
            grab()  # every camera triggered, its frame thrown away: a retry
            return grab()

        sensor.cameras.grab = twice
        again = sensor.measure(4, 10.0)
        sensor.cameras.grab = grab
        devices.robot.move_joints(away, 0.25)
        devices.robot.move_joints(here, 0.25)
        later = sensor.measure(4, 10.0)
    np.testing.assert_array_equal(again.xyz, first.xyz)
    np.testing.assert_array_equal(again.cov, first.cov)
    assert np.abs(later.xyz - first.xyz).max() > 1e-4


def test_a_target_out_of_view_is_no_target_after_three_sets():
    config = cell_for(FAMILY)
    with mock_devices(config) as devices:
        sensor, _ = _rig(devices)
        away = np.radians(config.robot.home_deg) + np.radians([70.0, 0, 0, 0, 0, 0])
        devices.robot.move_joints(away, 0.25)
        grabbed = {"n": 0}
        grab = sensor.cameras.grab

        def counting():
            grabbed["n"] += 1
            return grab()

        sensor.cameras.grab = counting
        with pytest.raises(NoTargetError, match=r"rig: no set measured the target \(set 0: "):
            sensor.measure(20, 10.0)
        assert grabbed["n"] <= 4  # gave up after three sets (one more may be under way)


def test_without_a_protocol_twin_the_frames_go_in_process_and_keep_images(tmp_path, caplog):
    base = cell_for(FAMILY)
    rig = base.sensor[-1]
    files = FilesRigOptions(
        directory=str(tmp_path / "none"),
        cameras=[CameraOptions(name=c.name) for c in rig.capture.cameras],
    )
    changed = rig.model_copy(update={"capture": files, "keep_images": str(tmp_path / "kept")})
    config = base.model_copy(update={"sensor": [*base.sensor[:-1], changed]})
    with caplog.at_level("WARNING"), mock_devices(config) as devices:
        sensor, twin = _rig(devices)
        assert twin.server is None
        devices.robot.move_joints(_near_home(config, 2), 0.25)
        s = sensor.measure(3, 10.0)
        assert s.n == 3
    assert 'backend "files" has no protocol twin' in caplog.text
    sets = sorted((tmp_path / "kept" / "rig").iterdir())
    assert len(sets) == 3
    assert sorted(p.name for p in sets[0].iterdir()) == [f"cam{k}.png" for k in range(4)]


def test_the_rig_and_target_files_are_found_beside_the_configuration(tmp_path):
    (tmp_path / "sub").mkdir()
    for name in ("mock-rig.toml", "mock-target.toml"):
        (tmp_path / "sub" / name).write_text((ROOT / "config" / name).read_text())
    text = (ROOT / "config" / "mock-cell.toml").read_text()
    (tmp_path / "sub" / "cell.toml").write_text(text)
    config = load_config(tmp_path / "sub" / "cell.toml")
    rig = config.sensor[-1]
    assert rig.rig_file == str(tmp_path / "sub" / "mock-rig.toml")
    assert rig.target_file == str(tmp_path / "sub" / "mock-target.toml")
    assert rig.endpoint() == "192.168.10.21, 192.168.10.22, 192.168.10.23, 192.168.10.24"
