"""The shared motion model of the controller twins, and the brand-neutral cell pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.mocks.motion import JointMove


def test_constant_speed_move_takes_travel_over_speed() -> None:
    m = JointMove(np.zeros(6), np.array([10.0, -30.0, 0, 0, 0, 5.0]), v=15.0)
    assert m.duration == pytest.approx(2.0)
    q, qd = m.at(1.0)
    np.testing.assert_allclose(q, [5.0, -15.0, 0, 0, 0, 2.5])
    np.testing.assert_allclose(qd, [5.0, -15.0, 0, 0, 0, 2.5])  # leading joint at 15/s
    q, qd = m.at(2.5)
    np.testing.assert_array_equal(q, m.q1)
    assert not qd.any() and m.done(2.0) and not m.done(1.99)


def test_trapezoid_reaches_cruise_and_integrates_to_the_target() -> None:
    m = JointMove(np.zeros(2), np.array([2.0, 1.0]), v=1.0, a=2.0)
    # 0.5 s up to 1 rad/s (0.25 rad), 1.5 s cruise, 0.5 s down: 2.5 s in all.
    assert m.duration == pytest.approx(2.5)
    ts = np.linspace(0.0, m.duration, 20001)
    speeds = np.array([m.at(t)[1][0] for t in ts])
    assert speeds.max() == pytest.approx(1.0)
    assert np.trapezoid(speeds, ts) == pytest.approx(2.0, abs=1e-6)
    assert m.at(0.5)[0][0] == pytest.approx(0.25)


def test_short_move_is_triangular() -> None:
    m = JointMove(np.zeros(1), np.ones(1) * 0.5, v=10.0, a=2.0)
    assert m.duration == pytest.approx(2 * math.sqrt(0.25))
    assert m.at(m.duration / 2)[1][0] == pytest.approx(1.0)  # a·t at the apex


def test_distance_times_the_move_by_another_measure() -> None:
    # A linear move: timed on the tool's 0.2 m at 0.1 m/s, whatever the joints travel.
    m = JointMove(np.zeros(6), np.full(6, 1.5), v=0.1, distance=0.2)
    assert m.duration == pytest.approx(2.0)
    np.testing.assert_allclose(m.at(1.0)[0], np.full(6, 0.75))


def test_no_travel_is_done_at_once_and_shapes_must_match() -> None:
    m = JointMove(np.ones(6), np.ones(6), v=1.0, a=1.0)
    assert m.duration == 0.0 and m.done(0.0)
    with pytest.raises(ValueError, match="shape"):
        JointMove(np.zeros(6), np.zeros(5), v=1.0)


def test_the_cell_pose_is_brand_neutral_and_each_twin_converts_it() -> None:
    from scipy.spatial.transform import Rotation

    from cellcal.commands.run import bundled_mock_cell
    from cellcal.files.models import load_model
    from cellcal.mocks.modbus.server import xyzabc
    from cellcal.mocks.simulated_cell import SimulatedCell
    from cellcal.mocks.ur.server import CellInURUnits

    config = bundled_mock_cell()[0]
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed=3)
    q = np.radians([10.0, -60.0, 70.0, 20.0, 45.0, -30.0])
    T = cell.flange_pose(q)
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    # The Modbus pose registers: mm and KUKA's Z-Y-X angles of the same rotation.
    x = xyzabc(T)
    np.testing.assert_allclose(x[:3], T[:3, 3])
    R = Rotation.from_euler("ZYX", x[3:], degrees=True).as_matrix()
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    # UR's units: m and a rotation vector; its inverse finds the joints again.
    ur = CellInURUnits(cell)
    pose = ur.fk(q)
    np.testing.assert_allclose(pose[:3] * 1000.0, T[:3, 3])
    np.testing.assert_allclose(Rotation.from_rotvec(pose[3:]).as_matrix(), T[:3, :3], atol=1e-12)
    back = ur.ik(pose, q + 0.05)
    assert back is not None
    np.testing.assert_allclose(back, q, atol=1e-8)
