"""Fusing sensors' estimates of one point: weights, χ², frames."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.calib.fusion import Estimate, carried, fuse, in_base
from cellcal.errors import InputError
from tests.lazy import Rotation


def test_the_more_certain_sensor_dominates_axis_by_axis():
    a = Estimate("tracker", np.array([0.0, 0.0, 0.0]), np.diag([0.01, 0.01, 1.0]) ** 2)
    b = Estimate("rig", np.array([1.0, 1.0, 1.0]), np.diag([1.0, 1.0, 0.01]) ** 2)
    f = fuse([a, b])
    np.testing.assert_allclose(f.xyz, [1e-4, 1e-4, 1 - 1e-4], atol=2e-8)
    np.testing.assert_allclose(np.sqrt(np.diag(f.cov)), [0.01, 0.01, 0.01], rtol=1e-4)
    assert f.sensors == ("tracker", "rig") and f.dof == 3
    assert fuse([a]).chi2 is None
    with pytest.raises(InputError):
        fuse([])


def test_chi2_per_degree_of_freedom_is_one_when_the_covariances_are_true():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(3, 3))
    C1 = A @ A.T * 0.01 + np.eye(3) * 1e-3
    C2 = np.diag([0.02, 0.05, 0.3]) ** 2
    L1, L2 = np.linalg.cholesky(C1), np.linalg.cholesky(C2)
    truth = np.array([100.0, -20.0, 5.0])
    chi2 = [
        fuse(
            [
                Estimate("a", truth + L1 @ rng.normal(size=3), C1),
                Estimate("b", truth + L2 @ rng.normal(size=3), C2),
            ]
        ).chi2
        for _ in range(4000)
    ]
    assert np.mean(chi2) / 3 == pytest.approx(1.0, abs=0.06)


def test_a_point_goes_to_the_base_and_along_the_flange():
    R = Rotation.from_euler("xyz", [10, -40, 120], degrees=True).as_matrix()
    T_sensor_base = np.eye(4)
    T_sensor_base[:3, :3] = R
    T_sensor_base[:3, 3] = [1000.0, -200.0, 50.0]
    p_base = np.array([700.0, 100.0, 900.0])
    cov_base = np.diag([0.01, 0.02, 0.03])
    m = R @ p_base + T_sensor_base[:3, 3]
    e = in_base("rig", m, R @ cov_base @ R.T, T_sensor_base)
    np.testing.assert_allclose(e.xyz, p_base, atol=1e-9)
    np.testing.assert_allclose(e.cov, cov_base, atol=1e-12)
    R_flange = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    moved = carried(e, R_flange, np.array([0.0, 0.0, 100.0]), np.array([0.0, 0.0, 130.0]))
    np.testing.assert_allclose(moved.xyz, p_base + np.array([30.0, 0.0, 0.0]), atol=1e-9)
