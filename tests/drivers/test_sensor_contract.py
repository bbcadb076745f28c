"""One contract every position-sensor family of the registry passes, built by the
device factory from a cell configuration (in mock mode its real driver against its
twin): n samples of the target at the robot's pose, with timestamps, in the sensor's
frame, where the simulated truth puts them. A family added to the table is picked up
here. The transport- and fault-level tests of each driver live beside it."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.families import families
from tests.drivers.families import cell_for, mock_devices

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60)]

SENSORS = families("sensor")


@pytest.mark.parametrize("family", SENSORS, ids=[f.tag for f in SENSORS])
def test_contract(family):
    config = cell_for(family)
    name = config.sensor[-1].name
    with mock_devices(config) as devices:
        setting = next(s for s in devices.sensors if s.sensor.name == name)
        sensor, cell = setting.sensor, devices.simulated_cell
        assert type(sensor).__name__ == family.device.rpartition(":")[2]
        q = np.radians(config.robot.home_deg) + np.radians([8.0, -5.0, 4.0, 10.0, -6.0, 15.0])
        devices.robot.move_joints(q, 0.25)
        series = sensor.measure(12, setting.rate_hz)
        assert series.sensor == name and series.n == 12 and series.retries == 0
        assert series.xyz.shape == (12, 3) and np.isfinite(series.xyz).all()
        assert (np.diff(series.device_time) > 0).all()
        assert (np.diff(series.host_time) >= 0).all()
        truth = cell.true_position(name)
        # Within 5 sigma of the truth of the mean, whatever the sensor's noise model.
        sigma = max(series.std.max(), 1e-3) / np.sqrt(series.n)
        assert np.linalg.norm(series.mean - truth) < 5 * sigma * np.sqrt(3)
        # The target follows the robot.
        devices.robot.move_joints(np.radians(config.robot.home_deg), 0.25)
        again = sensor.measure(3, setting.rate_hz)
        assert np.linalg.norm(again.mean - series.mean) > 10.0
