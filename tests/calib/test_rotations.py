"""cellcal's numpy rotation conversions against scipy's ``Rotation`` (the reference the
module replaces only to keep scipy.spatial out of every process's start), on random
rotations and at the edges: identity, tiny angles, half turns, gimbal lock."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from cellcal.calib import rotations as rot
from tests.lazy import Rotation


@functools.cache
def _rotations(kind: str) -> Rotation:
    """500 random rotations, or the edges: each axis at angles from 0 to a half turn."""
    if kind == "random":
        return Rotation.random(500, random_state=7)
    axes = np.vstack([np.eye(3), np.random.default_rng(20261129).normal(size=(6, 3))])
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = [0.0, 1e-12, 1e-7, 9.99e-4, 1.001e-3, 0.5, np.pi / 2, np.pi - 1e-7, np.pi]
    return Rotation.from_rotvec(np.array([a * angle for a in axes for angle in angles]))


@pytest.fixture(params=["random", "edges"])
def r(request: pytest.FixtureRequest) -> Rotation:
    return _rotations(request.param)


def test_rotation_vectors_match_scipy_both_ways(r: Rotation):
    R = r.as_matrix()
    np.testing.assert_allclose(rot.matrix_from_rotvec(r.as_rotvec()), R, atol=2e-15)
    w = rot.rotvec_from_matrix(R)
    # a half turn is the same either way round: compare the rotations, then the vectors
    np.testing.assert_allclose(rot.matrix_from_rotvec(w), R, atol=2e-15)
    away = np.linalg.norm(w, axis=1) < np.pi - 1e-6
    np.testing.assert_allclose(w[away], r.as_rotvec()[away], atol=1e-14, rtol=1e-12)
    assert (np.linalg.norm(w, axis=1) <= np.pi + 1e-15).all()


def test_quaternions_match_scipy_w_first_and_w_not_negative(r: Rotation):
    R = r.as_matrix()
    q = rot.quaternion_from_matrix(R)
    ref = r.as_quat(canonical=True)[:, [3, 0, 1, 2]]
    assert (q[:, 0] >= 0).all()
    # w = 0 leaves the sign free: compare up to sign there
    same = np.where(np.sum(q * ref, axis=1, keepdims=True) < 0, -ref, ref)
    np.testing.assert_allclose(q, same, atol=1e-15)
    np.testing.assert_allclose(rot.matrix_from_quaternion(q), R, atol=2e-15)
    np.testing.assert_allclose(rot.matrix_from_quaternion(3.0 * q), R, atol=2e-15)


def test_a_matrix_a_little_off_orthonormal_gives_the_nearby_rotation():
    R = _rotations("random").as_matrix()[:50]
    off = R + np.random.default_rng(1).normal(scale=1e-9, size=R.shape)
    q = rot.quaternion_from_matrix(off)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(rot.matrix_from_quaternion(q), R, atol=1e-8)
    for k in range(50):
        near = rot.nearest_rotation(off[k])
        np.testing.assert_allclose(near @ near.T, np.eye(3), atol=1e-15)
        assert np.linalg.det(near) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(near, R[k], atol=3e-9)
    reflected = R[0] @ np.diag([1.0, 1.0, -1.0])
    assert np.linalg.det(rot.nearest_rotation(reflected)) == pytest.approx(1.0)


def test_euler_angles_match_scipy_and_survive_gimbal_lock():
    abc = np.random.default_rng(2).uniform(
        [-np.pi, -np.pi / 2, -np.pi], [np.pi, np.pi / 2, np.pi], size=(300, 3)
    )
    R = rot.matrix_from_euler_xyz(abc)
    np.testing.assert_allclose(R, Rotation.from_euler("xyz", abc).as_matrix(), atol=2e-15)
    zyx = rot.euler_zyx_from_matrix(R)
    np.testing.assert_allclose(zyx, abc[:, ::-1], atol=1e-9)
    ref = Rotation.from_matrix(R).as_euler("ZYX")
    np.testing.assert_allclose(zyx, ref, atol=1e-9)
    for b in (np.pi / 2, -np.pi / 2):
        locked = rot.matrix_from_euler_xyz(np.array([0.7, b, -0.4]))
        a_b_c = rot.euler_zyx_from_matrix(locked)
        assert a_b_c[1] == pytest.approx(b) and a_b_c[2] == 0.0
        # the same rotation, told with C = 0
        back = rot.matrix_from_euler_xyz(a_b_c[::-1])
        np.testing.assert_allclose(back, locked, atol=1e-12)


def test_one_rotation_and_many_keep_their_shapes():
    w = np.array([0.1, -0.2, 0.3])
    assert rot.matrix_from_rotvec(w).shape == (3, 3)
    assert rot.rotvec_from_matrix(rot.matrix_from_rotvec(w)).shape == (3,)
    assert rot.quaternion_from_matrix(np.eye(3)).tolist() == [1.0, 0.0, 0.0, 0.0]
    many = np.tile(w, (2, 4, 1))
    assert rot.matrix_from_rotvec(many).shape == (2, 4, 3, 3)
    np.testing.assert_allclose(rot.rotvec_from_matrix(rot.matrix_from_rotvec(many)), many)
