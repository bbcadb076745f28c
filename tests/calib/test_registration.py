"""Registration: the paper's Table 4, exact recovery, statistics and every bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcal.calib.registration import METHODS, apply_fit, fit_rigid
from cellcal.calib.registration_batch import fit_rigid_batch, leave_one_out
from cellcal.errors import (
    ConvergenceError,
    DegenerateGeometryError,
    InputError,
    MirroredCorrespondenceError,
    UserError,
)
from tests.conftest import rigid_problem
from tests.lazy import Rotation, least_squares

LS = ("svd", "quaternion", "rodrigues", "small-angle")

# --------------------------------------------------------------------- the paper's Table 4


@pytest.mark.parametrize("method", LS)
def test_table4_least_squares_beats_every_printed_row(table4, method):
    src, dst = table4
    fit = fit_rigid(src, dst, method=method)
    np.testing.assert_allclose(
        fit.residual_norms, [0.0138, 0.0168, 0.0231, 0.0229, 0.0316], atol=5e-5
    )
    assert fit.rms == pytest.approx(0.0225, abs=5e-5)
    # The paper prints RMS 0.033, 0.024, 0.027, 0.028, 0.025 mm: least squares is lower.
    assert fit.rms < min(0.033, 0.024, 0.027, 0.028, 0.025)


def test_table4_characteristic_line_p1p2_p2p3(table4):
    src, dst = table4
    fit = fit_rigid(src, dst, method="line", lines=([0, 1], [1, 2]))
    assert fit.rms == pytest.approx(0.025, abs=0.001)
    assert fit.rms > fit_rigid(src, dst).rms
    assert fit.support_points == ((0, 1), (1, 2))
    assert len(fit.line_steps) == 3
    # The method makes line B coincide exactly and puts A in the plane of A' and B'.
    fitted = apply_fit(fit, src)
    b_fit, b_dst = fitted[2] - fitted[1], dst[2] - dst[1]
    cross = np.cross(b_fit, b_dst) / (np.linalg.norm(b_fit) * np.linalg.norm(b_dst))
    assert np.linalg.norm(cross) < 1e-12
    np.testing.assert_allclose(0.5 * (fitted[0] + fitted[1]), 0.5 * (dst[0] + dst[1]), atol=1e-9)


def test_three_point_on_table4_is_worse_than_least_squares(table4):
    src, dst = table4
    fit = fit_rigid(src, dst, method="three-point", three_points=[0, 1, 2])
    assert fit.rms > fit_rigid(src, dst).rms
    assert fit.support_points == ((0, 1, 2),)
    assert fit.covariance is None


# --------------------------------------------------------------------- characteristic line


def _triad(b1, a1, b2, a2):
    """Independent TRIAD with b as primary: R maps frame 1 directions onto frame 2."""

    def frame(b, a):
        e1 = b / np.linalg.norm(b)
        e3 = np.cross(b, a)
        e3 /= np.linalg.norm(e3)
        return np.column_stack([e1, np.cross(e3, e1), e3])

    return frame(b2, a2) @ frame(b1, a1).T


def test_characteristic_line_equals_triad_with_b_primary():
    P, Q, _, _ = rigid_problem(3, n=12, noise=0.05)
    fit = fit_rigid(P, Q, method="line", lines=([0, 5], [2, 7]))
    R = _triad(P[7] - P[2], P[5] - P[0], Q[7] - Q[2], Q[5] - Q[0])
    np.testing.assert_allclose(fit.R, R, atol=1e-12)


def test_chain_is_rotation_about_axis_through_point():
    from cellcal.calib.characteristic_line import chain

    rng = np.random.default_rng(4)
    axis, point = rng.normal(size=3), rng.normal(size=3) * 100
    theta = 1.234
    step = chain(axis, theta, point)
    R = Rotation.from_rotvec(theta * axis / np.linalg.norm(axis)).as_matrix()
    x = rng.normal(size=(5, 3)) * 50
    expected = (x - point) @ R.T + point
    got = x @ step.T[:3, :3].T + step.T[:3, 3]
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # The paper's printed Eq. 4 (Rz(−θ)) would rotate the other way: the sign matters.
    assert not np.allclose(got, (x - point) @ R + point, atol=1e-3)


def test_generalised_line_through_several_points():
    P, Q, R, t = rigid_problem(5, n=30)
    fit = fit_rigid(P, Q, method="line", lines=([0, 1, 2, 3], [4, 5, 6]))
    np.testing.assert_allclose(fit.R, R, atol=1e-9)
    np.testing.assert_allclose(fit.t, t, atol=1e-6)


def test_line_degenerate_parallel_lines():
    P, Q, _, _ = rigid_problem(6, n=10)
    P[3] = P[2] + (P[1] - P[0])  # B parallel to A
    Q[3] = Q[2] + (Q[1] - Q[0])
    with pytest.raises(DegenerateGeometryError, match="undetermined"):
        fit_rigid(P, Q, method="line", lines=([0, 1], [2, 3]))


def test_line_with_coincident_points():
    P, Q, _, _ = rigid_problem(7, n=10)
    P[1], Q[1] = P[0], Q[0]
    with pytest.raises(DegenerateGeometryError, match="coincide"):
        fit_rigid(P, Q, method="line", lines=([0, 1], [2, 3]))


def test_line_antiparallel_first_step():
    """A rotation of exactly 180° about an axis normal to A makes A′ antiparallel to A."""
    P, _, _, _ = rigid_problem(8, n=10)
    a = P[1] - P[0]
    axis = np.cross(a, [0.3, 0.2, 0.9])
    R = Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)).as_matrix()
    Q = P @ R.T + [1.0, 2.0, 3.0]
    fit = fit_rigid(P, Q, method="line", lines=([0, 1], [2, 3]))
    np.testing.assert_allclose(fit.R, R, atol=1e-9)


# --------------------------------------------------------------------- exact recovery


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 40),
    method=st.sampled_from([m for m in METHODS if m != "small-angle"]),
)
def test_random_rigid_transforms_recovered_without_noise(seed, n, method):
    P, Q, R, t = rigid_problem(seed, n=n)
    fit = fit_rigid(P, Q, method=method)
    np.testing.assert_allclose(fit.R, R, atol=1e-9)
    np.testing.assert_allclose(fit.t, t, atol=1e-9 * 5000)
    assert fit.rms < 1e-9


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 179.0))
def test_small_angle_iterated_recovers_any_angle_below_180(seed, angle):
    P, Q, R, _ = rigid_problem(seed, n=10, angle_deg=angle)
    fit = fit_rigid(P, Q, method="small-angle")
    np.testing.assert_allclose(fit.R, R, atol=1e-9)


@pytest.mark.parametrize("method", ["rodrigues", "rodrigues-linear", "svd", "quaternion"])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_exact_180_degree_rotations(method, axis):
    P, _, _, _ = rigid_problem(9, n=8)
    R = Rotation.from_rotvec(np.pi * np.eye(3)[axis]).as_matrix()
    Q = P @ R.T
    np.testing.assert_allclose(fit_rigid(P, Q, method=method).R, R, atol=1e-9)


def test_small_angle_at_180_degrees_is_right_or_says_so():
    """Gauss–Newton from the identity may not start at exactly 180°: never a wrong answer."""
    raised = 0
    for seed in range(40):
        P, _, _, _ = rigid_problem(seed, n=8)
        axis = np.random.default_rng(seed).normal(size=3)
        R = Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)).as_matrix()
        try:
            fit = fit_rigid(P, P @ R.T, method="small-angle")
        except ConvergenceError as exc:
            assert "svd" in str(exc)
            raised += 1
        else:
            np.testing.assert_allclose(fit.R, R, atol=1e-9)
    # Cube corners turned by 180° about z: the identity is a stationary point (a saddle).
    cube = np.array([[x, y, z] for x in (0, 200) for y in (0, 100) for z in (0, 50)], float)
    Rz = np.diag([-1.0, -1.0, 1.0])
    with pytest.raises(ConvergenceError, match="saddle"):
        fit_rigid(cube, cube @ Rz.T, method="small-angle")


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), method=st.sampled_from(LS))
def test_invariant_to_point_order(seed, method):
    P, Q, _, _ = rigid_problem(seed, n=15, noise=0.05)
    perm = np.random.default_rng(seed).permutation(15)
    a = fit_rigid(P, Q, method=method)
    b = fit_rigid(P[perm], Q[perm], method=method)
    np.testing.assert_allclose(a.T, b.T, atol=1e-9)
    np.testing.assert_allclose(a.residual_norms[perm], b.residual_norms, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    c=st.floats(1e-6, 1e6),
    method=st.sampled_from((*LS, "rodrigues-linear")),
)
def test_uniform_constant_weights_change_nothing(seed, c, method):
    P, Q, _, _ = rigid_problem(seed, n=12, noise=0.05)
    a = fit_rigid(P, Q, method=method)
    b = fit_rigid(P, Q, method=method, weights=np.full(12, c))
    np.testing.assert_allclose(a.T, b.T, atol=1e-9)


def test_integer_weight_equals_repeated_point():
    P, Q, _, _ = rigid_problem(11, n=10, noise=0.1)
    w = np.ones(10)
    w[3] = 3.0
    a = fit_rigid(P, Q, weights=w)
    b = fit_rigid(np.vstack([P, P[3], P[3]]), np.vstack([Q, Q[3], Q[3]]))
    np.testing.assert_allclose(a.T, b.T, atol=1e-10)


@pytest.mark.parametrize("method", LS)
def test_all_least_squares_methods_agree_on_noisy_data(method):
    P, Q, _, _ = rigid_problem(12, n=30, noise=0.2)
    np.testing.assert_allclose(fit_rigid(P, Q, method=method).T, fit_rigid(P, Q).T, atol=1e-9)


# --------------------------------------------------------------------- precision


def test_float32_input_is_computed_in_float64():
    P, Q, _, _ = rigid_problem(13, n=10, noise=0.01)
    P32, Q32 = P.astype(np.float32), Q.astype(np.float32)
    a = fit_rigid(P32, Q32)
    b = fit_rigid(P32.astype(np.float64), Q32.astype(np.float64))
    np.testing.assert_array_equal(a.T, b.T)
    assert a.T.dtype == np.float64


def test_huge_coordinate_offsets():
    P, _, R, t = rigid_problem(14, n=10)
    offset = np.array([6.4e9, -3.1e9, 1.2e9])  # mm: a datum thousands of km away
    P = P + offset
    Q = P @ R.T + t
    fit = fit_rigid(P, Q)
    np.testing.assert_allclose(fit.R, R, atol=1e-12)
    assert fit.rms < 1e-5  # representation limit of 1e9-mm coordinates in float64
    naive = P @ fit.R.T + fit.t
    assert np.max(np.abs(naive - Q)) < 1e-4


# --------------------------------------------------------------------- scale, weights, robust


def test_umeyama_scale():
    P, Q, R, t = rigid_problem(15, n=10)
    Q = 1.0004 * (P @ R.T) + t
    fit = fit_rigid(P, Q, scale=True)
    assert fit.scale == pytest.approx(1.0004, abs=1e-12)
    assert fit.rms < 1e-8
    assert fit.dof == 3 * 10 - 7
    assert fit.scale_std == 0.0 or fit.scale_std < 1e-9


def test_scale_mismatch_warns_without_scale():
    P, _Q, R, t = rigid_problem(16, n=10)
    fit = fit_rigid(P, (P @ R.T) / 1000.0 + t)
    assert any("units" in w for w in fit.warnings)


def test_full_covariances_minimise_the_mahalanobis_residual():
    P, Q, _R, _t = rigid_problem(17, n=15)
    rng = np.random.default_rng(17)
    A = rng.normal(size=(15, 3, 3)) * 0.05
    C_dst = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(3)
    Q = Q + np.einsum("nij,nj->ni", np.linalg.cholesky(C_dst), rng.normal(size=(15, 3)))
    C_src = np.broadcast_to(np.diag([1e-4, 4e-4, 1e-4]), (15, 3, 3)).copy()
    fit = fit_rigid(P, Q, cov_src=C_src, cov_dst=C_dst)

    # Independent check: scipy least squares on whitened residuals, with Σᵢ at the solution.
    Sig = C_dst + np.einsum("ij,njk,lk->nil", fit.R, C_src, fit.R)
    L = np.linalg.cholesky(np.linalg.inv(Sig))

    def resid(x):
        Rx = Rotation.from_rotvec(x[:3]).as_matrix()
        r = Q - P @ Rx.T - x[3:]
        return np.einsum("nji,nj->ni", L, r).ravel()

    x0 = np.concatenate([Rotation.from_matrix(fit.R).as_rotvec() + 1e-3, fit.t + 0.1])
    ref = least_squares(resid, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(Rotation.from_rotvec(ref.x[:3]).as_matrix(), fit.R, atol=1e-9)
    np.testing.assert_allclose(ref.x[3:], fit.t, atol=1e-6)
    # It differs from the unweighted answer (the weighting did something).
    assert not np.allclose(fit_rigid(P, Q).t, fit.t, atol=1e-4)


def test_isotropic_equal_covariances_equal_unweighted():
    P, Q, _, _ = rigid_problem(18, n=12, noise=0.05)
    sig = np.full((12, 3), 0.02)
    np.testing.assert_allclose(fit_rigid(P, Q, cov_dst=sig).T, fit_rigid(P, Q).T, atol=1e-10)


@pytest.mark.parametrize("robust", ["huber", "tukey", "ransac"])
def test_robust_options_reject_gross_outliers(robust):
    P, Q, R, t = rigid_problem(19, n=25, noise=0.01)
    Q[[4, 17]] += [[5.0, -3.0, 2.0], [0.0, 8.0, 1.0]]
    plain = fit_rigid(P, Q)
    fit = fit_rigid(P, Q, robust=robust)
    truth = P @ R.T + t
    err = np.linalg.norm(apply_fit(fit, P) - truth, axis=1).max()
    assert err < 0.05 < np.linalg.norm(apply_fit(plain, P) - truth, axis=1).max()
    assert not fit.inliers[4] and not fit.inliers[17]
    if robust != "huber":
        assert fit.inliers.sum() == 23
    assert fit.rms < 0.05 < plain.rms


def test_ransac_threshold_and_seed_reproducible():
    P, Q, _, _ = rigid_problem(20, n=40, noise=0.01)
    Q[:5] += 3.0
    a = fit_rigid(P, Q, robust="ransac", ransac_threshold=0.1, seed=1)
    b = fit_rigid(P, Q, robust="ransac", ransac_threshold=0.1, seed=1)
    np.testing.assert_array_equal(a.T, b.T)
    assert a.inliers.sum() == 35


# --------------------------------------------------------------------- statistics


def test_covariance_matches_monte_carlo():
    """The first-order covariance predicts the scatter of the fitted transform."""
    P, _, R, t = rigid_problem(21, n=12)
    rng = np.random.default_rng(21)
    sigma = 0.05
    rv, tt, pred = [], [], []
    for _ in range(400):
        Q = P @ R.T + t + rng.normal(0, sigma, P.shape)
        fit = fit_rigid(P, Q)
        rv.append(Rotation.from_matrix(fit.R @ R.T).as_rotvec())
        tt.append(fit.t - t)
        pred.append(np.sqrt(np.diag(fit.covariance)))
    observed = np.concatenate([np.std(rv, axis=0), np.std(tt, axis=0)])
    predicted = np.mean(pred, axis=0)
    np.testing.assert_allclose(observed, predicted, rtol=0.15)


def test_sigma0_and_dof():
    P, Q, _, _ = rigid_problem(22, n=200, noise=0.03)
    fit = fit_rigid(P, Q)
    assert fit.dof == 3 * 200 - 6
    assert fit.sigma0 == pytest.approx(0.03, rel=0.1)
    assert 1.0 <= fit.condition < 10.0


def test_condition_grows_for_nearly_collinear_points():
    P, _Q, _, _ = rigid_problem(23, n=10)
    flat = P.copy()
    flat[:, 1:] = flat[:, 1:] * 1e-4 + P[0, 1:]
    R = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    fit = fit_rigid(flat, flat @ R.T)
    assert fit.condition > 1e6
    assert any("collinear" in w for w in fit.warnings)


def test_leave_one_out_batched_equals_loop():
    P, Q, _, _ = rigid_problem(24, n=15, noise=0.05)
    fast = leave_one_out(P, Q)  # svd: one batched problem
    slow = leave_one_out(P, Q, method="quaternion")  # a loop over fit_rigid
    np.testing.assert_allclose(fast.errors, slow.errors, atol=1e-9)
    assert fast.rms > fit_rigid(P, Q).rms
    assert fast.skipped == 0


def test_leave_one_out_skips_points_a_line_needs(table4):
    src, dst = table4
    loo = leave_one_out(src, dst, method="line", lines=([0, 1], [1, 2]))
    assert loo.skipped == 3
    assert np.isnan(loo.norms[:3]).all() and np.isfinite(loo.norms[3:]).all()


def test_batch_equals_single_fits():
    probs = [rigid_problem(s, n=10, noise=0.02) for s in range(30)]
    P = np.stack([p[0] for p in probs])
    Q = np.stack([p[1] for p in probs])
    b = fit_rigid_batch(P, Q)
    for i in range(30):
        f = fit_rigid(P[i], Q[i])
        np.testing.assert_allclose(b.T[i], f.T, atol=1e-9)
        assert b.rms[i] == pytest.approx(f.rms, abs=1e-12)
    assert not b.degenerate.any()


def test_batch_flags_degenerate_problems():
    P = np.zeros((2, 4, 3))
    P[0] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    P[1] = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]
    b = fit_rigid_batch(P, P)
    assert list(b.degenerate) == [False, True]


def test_result_is_frozen():
    P, Q, _, _ = rigid_problem(25, n=5)
    fit = fit_rigid(P, Q)
    with pytest.raises(AttributeError):
        fit.rms = 0.0  # type: ignore[misc]


# --------------------------------------------------------------------- bad input


def test_fewer_than_three_points():
    with pytest.raises(DegenerateGeometryError, match="at least 3"):
        fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))


def test_mismatched_shapes():
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="correspond"):
        fit_rigid(rng.random((5, 3)), rng.random((4, 3)))
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        fit_rigid(rng.random((5, 2)), rng.random((5, 2)))
    with pytest.raises(InputError, match="not an array"):
        fit_rigid([[1, 2, "x"]] * 4, rng.random((4, 3)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_and_inf(bad):
    P, Q, _, _ = rigid_problem(26, n=6)
    Q[4, 1] = bad
    with pytest.raises(InputError, match="point 4 is not finite"):
        fit_rigid(P, Q)


def test_duplicates_that_collapse_the_set():
    P, Q, _, _ = rigid_problem(27, n=6)
    P = np.vstack([P[:2]] * 3)
    Q = np.vstack([Q[:2]] * 3)
    with pytest.raises(DegenerateGeometryError, match=r"collinear.*2 distinct"):
        fit_rigid(P, Q)


def test_all_points_coincide():
    rng = np.random.default_rng(0)
    with pytest.raises(DegenerateGeometryError, match="coincide"):
        fit_rigid(np.ones((5, 3)), rng.random((5, 3)))


@pytest.mark.parametrize("method", METHODS)
def test_collinear_points(method):
    P = np.outer(np.arange(6.0), [1.0, 2.0, 3.0]) + 100.0
    Q = P + 5.0
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        fit_rigid(P, Q, method=method)


@pytest.mark.parametrize("method", METHODS)
def test_mirrored_correspondence(method):
    P, Q, _, _ = rigid_problem(28, n=10)
    Q[:, 0] *= -1.0  # a left-handed destination frame
    with pytest.raises(MirroredCorrespondenceError, match="mirrored"):
        fit_rigid(P, Q, method=method)


def test_planar_points_are_not_mistaken_for_a_mirror():
    rng = np.random.default_rng(29)
    P = np.column_stack([rng.uniform(-100, 100, (8, 2)), np.zeros(8)])
    R = Rotation.from_rotvec([0.2, 0.1, 2.0]).as_matrix()
    fit = fit_rigid(P, P @ R.T + 7.0)
    np.testing.assert_allclose(fit.R, R, atol=1e-12)


def test_option_errors():
    P, Q, _, _ = rigid_problem(30, n=6)
    for kwargs, match in [
        ({"method": "nope"}, "unknown method"),
        ({"robust": "cauchy"}, "unknown robust"),
        ({"method": "three-point", "weights": np.ones(6)}, "least-squares"),
        ({"method": "line", "scale": True}, "least-squares"),
        ({"weights": np.ones(5)}, "expected 6"),
        ({"weights": -np.ones(6)}, "non-negative"),
        ({"weights": np.ones(6), "cov_dst": np.ones((6, 3))}, "either"),
        ({"cov_dst": np.ones((6, 2))}, "covariances"),
        ({"method": "line", "lines": ([0], [1, 2])}, "at least 2"),
        ({"method": "line", "lines": ([0, 9], [1, 2])}, "out of range"),
        ({"method": "three-point", "three_points": [0, 0, 1]}, "distinct"),
        ({"lines": ([0, 1], [1, 2])}, "only used by the line"),
        ({"robust": "ransac", "ransac_threshold": -1.0}, "positive"),
    ]:
        with pytest.raises(UserError, match=match):
            fit_rigid(P, Q, **kwargs)


def test_weights_leaving_fewer_than_three_points():
    P, Q, _, _ = rigid_problem(31, n=6)
    with pytest.raises(DegenerateGeometryError, match="fewer than 3"):
        fit_rigid(P, Q, weights=[1, 1, 0, 0, 0, 0])


def test_batch_flags_mirrored_problems():
    P, Q, _, _ = rigid_problem(32, n=10)
    b = fit_rigid_batch(np.stack([P, P]), np.stack([Q, Q * [1, 1, -1]]))
    assert list(b.mirrored) == [False, True]
    assert list(b.degenerate) == [False, False]


def test_robust_with_covariances_keeps_outliers_out():
    P, Q, R, _t = rigid_problem(33, n=20, noise=0.01)
    Q[7] += 5.0
    fit = fit_rigid(P, Q, robust="ransac", cov_dst=np.full((20, 3), 0.01))
    assert not fit.inliers[7]
    assert fit.rms < 0.05
    np.testing.assert_allclose(fit.R, R, atol=1e-3)


def test_covariance_weighting_far_from_the_origin():
    P, Q, _R, _t = rigid_problem(34, n=10, noise=0.01)
    far = np.array([2.0e7, -1.0e7, 5.0e6])  # 20 km: a site datum
    fit = fit_rigid(P + far, Q + far, cov_dst=np.full((10, 3), 0.01))
    ref = fit_rigid(P + far, Q + far)
    np.testing.assert_allclose(fit.R, ref.R, atol=1e-9)


def test_zero_uncertainty_in_both_files_is_a_user_error():
    P, _, _, _ = rigid_problem(35, n=6)
    sig = np.full((6, 3), 0.01)
    sig[:, 1] = 0.0  # no y uncertainty anywhere, frames parallel: Σᵢ singular
    with pytest.raises(InputError, match="point 0 has no uncertainty"):
        fit_rigid(P, P + 1.0, cov_src=sig, cov_dst=sig)


def test_condition_does_not_depend_on_weights_being_uneven():
    P, Q, _, _ = rigid_problem(36, n=12, noise=0.02)
    w = np.linspace(0.1, 10.0, 12)
    a = fit_rigid(P, Q, weights=w)
    b = fit_rigid(P, Q, weights=w * 7.0)
    assert a.condition == pytest.approx(b.condition, rel=1e-9)
    # The rotation block about the weighted centroid, computed directly.
    pc = (w @ P) / w.sum()
    X = (P - pc) @ a.R.T
    N = sum(wi * (x @ x * np.eye(3) - np.outer(x, x)) for wi, x in zip(w, X, strict=True))
    ev = np.linalg.eigvalsh(N)
    assert a.condition == pytest.approx(ev[2] / ev[0], rel=1e-9)


@pytest.mark.parametrize("method", ["rodrigues", "small-angle"])
def test_iterative_methods_on_nearly_collinear_points(method):
    P, _, _, _ = rigid_problem(37, n=10)
    P[:, 1:] = P[:, 1:] * 1e-3 + P[0, 1:]
    R = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    Q = P @ R.T + np.random.default_rng(37).normal(0, 0.01, P.shape)
    np.testing.assert_allclose(fit_rigid(P, Q, method=method).R, fit_rigid(P, Q).R, atol=1e-8)


def test_ransac_threshold_without_ransac_is_refused():
    P, Q, _, _ = rigid_problem(38, n=6)
    with pytest.raises(InputError, match="ransac_threshold"):
        fit_rigid(P, Q, ransac_threshold=1.0)


def test_batch_text_input_is_an_input_error():
    with pytest.raises(InputError, match="numbers"):
        fit_rigid_batch([[["a", "b", "c"]] * 3], [[["a", "b", "c"]] * 3])
