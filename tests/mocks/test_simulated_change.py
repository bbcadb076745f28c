"""`[simulation.change]`: the simulated cell after its calibration (issue 33) — a joint's
zero moved, a link stretched, the base shifted, the arm grown with its temperature — and
what is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.clock import SimulatedClock
from cellcal.config import config_from_dict
from cellcal.errors import ConfigError, InputError
from cellcal.files.models import load_model
from cellcal.mocks.simulated_cell import SimulatedCell
from tests.drivers.families import bundled_cells


def _cell(change: dict[str, object], clock: SimulatedClock | None = None) -> SimulatedCell:
    data = bundled_cells()[0].model_dump()
    data["simulation"]["change"] = change
    config = config_from_dict(data, "changed cell")
    return SimulatedCell(config, load_model(config.robot.model).model, clock=clock)


def test_a_joint_offset_and_a_link_change_move_only_those_parameters():
    before = _cell({})
    after = _cell({"joint_offset_deg": [0, 0.05, 0, 0, 0, 0], "link_mm": {"a2": 0.4, "d4": -0.2}})
    # same seed, same errors at calibration
    assert after.model_at_calibration == before.model
    for i, (b, a) in enumerate(zip(before.model.joints, after.model.joints, strict=True)):
        assert a.theta - b.theta == pytest.approx(math.radians(0.05) if i == 1 else 0.0, abs=1e-15)
        assert a.a - b.a == pytest.approx(0.4 if i == 1 else 0.0, abs=1e-12)
        assert a.d - b.d == pytest.approx(-0.2 if i == 3 else 0.0, abs=1e-12)
        assert (a.alpha, a.beta) == (b.alpha, b.beta)


def test_a_shifted_base_moves_every_point_by_the_shift():
    before, after = _cell({}), _cell({"base_shift_mm": [0.3, -0.2, 0.5]})
    q = np.radians([10.0, -40.0, 50.0, 5.0, -30.0, 20.0])
    for name in before.sensors:
        R = before.sensors[name].T_sensor_base[:3, :3]
        moved = after.true_position(name, q) - before.true_position(name, q)
        # the base (and the robot on it) moved by the shift, seen in the sensor's frame
        np.testing.assert_allclose(moved, R @ np.array([0.3, -0.2, 0.5]), atol=1e-9)


def test_a_change_that_does_not_fit_the_robot_is_one_line():
    with pytest.raises(InputError, match=r"joint_offset_deg: 5 values for a robot of 6 joints"):
        _cell({"joint_offset_deg": [0, 0, 0, 0, 0.1]})
    with pytest.raises(InputError, match=r"link_mm: a7: the robot has 6 joints"):
        _cell({"link_mm": {"a7": 0.1}})
    with pytest.raises(ConfigError, match=r"simulation\.change\.link_mm\.theta2"):
        _cell({"link_mm": {"theta2": 0.1}})  # lengths only (a, d)
    with pytest.raises(ConfigError, match=r"temperature_c: \[t_s, c\] points in increasing"):
        _cell({"temperature_c": [[0, 20], [0, 25]]})
    with pytest.raises(ConfigError, match=r"temperature_c: each c from -40 to 100"):
        _cell({"temperature_c": [[0, 20], [60, 400]]})
    with pytest.raises(ConfigError, match=r"simulation\.change\.thermal_mm_per_c"):
        _cell({"thermal_mm_per_c": 5})  # mm per °C of the whole reach: 1 at most


def test_the_arm_grows_with_the_temperature_profile_on_the_campaign_clock():
    clock = SimulatedClock()
    profile = {"thermal_mm_per_c": 0.02, "temperature_c": [[0, 20], [100, 30], [200, 30]]}
    cell, cold = _cell(profile, clock), _cell({})
    q = np.radians([10.0, -40.0, 50.0, 5.0, -30.0, 20.0])
    name = next(iter(cell.sensors))
    np.testing.assert_allclose(cell.true_position(name, q), cold.true_position(name, q))
    reach = sum(abs(j.a) + abs(j.d) for j in cold.model.joints)
    for t, grown_mm in ((50.0, 0.1), (100.0, 0.2), (1000.0, 0.2)):
        clock.sleep(t - clock.now())
        model = cell.model_now()
        assert sum(abs(j.a) + abs(j.d) for j in model.joints) == pytest.approx(reach + grown_mm)
        for j, c in zip(model.joints, cold.model.joints, strict=True):
            assert j.a == pytest.approx(c.a * (1 + grown_mm / reach))  # each in proportion
        moved = np.linalg.norm(cell.true_position(name, q) - cold.true_position(name, q))
        assert 0.2 * grown_mm < moved < grown_mm
