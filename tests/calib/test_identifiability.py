"""The identifiability analysis's correlations: the parameters it names as correlated and
their ρ, on Jacobians whose answer is known, and on one so ill-conditioned that inverting
JᵀJ gives negative variances."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from cellcal.calib.error_model import ParameterSpec
from cellcal.calib.identifiability import CORRELATION_WARN, analyse


def _specs(n: int) -> tuple[ParameterSpec, ...]:
    return tuple(ParameterSpec(f"a{k + 1}", "a", k + 1, "mm") for k in range(n))


def test_two_columns_at_a_small_angle_are_named_with_their_correlation():
    rng = np.random.default_rng(3)
    u, v, w = np.linalg.qr(rng.normal(size=(60, 3)))[0].T
    angle = 0.04  # rad: cos 0.9992, over the 0.9 that is reported
    J = np.column_stack([u, np.cos(angle) * u + np.sin(angle) * v, 5.0 * w])
    a = analyse(J, _specs(3))
    assert a.identified == (0, 1, 2)
    assert len(a.correlated) == 1
    first, second, rho = a.correlated[0]
    # for two unit columns at angle φ, orthogonal to the rest, ρ of the estimates = −cos φ
    assert (first, second) == ("a1", "a2") and rho == pytest.approx(-np.cos(angle), abs=1e-4)
    wide = np.column_stack([u, np.cos(0.6) * u + np.sin(0.6) * v, w])
    assert np.cos(0.6) < CORRELATION_WARN and analyse(wide, _specs(3)).correlated == ()


def test_an_ill_conditioned_set_still_gives_correlations_and_no_warning():
    # Kahan's matrix: every column far from the span of those before it, as pivoted QR
    # sees it, and yet a condition number of 1e10: (JᵀJ)⁻¹ has negative diagonals
    n, theta = 27, 0.8
    s, c = np.sin(theta), np.cos(theta)
    J = np.diag(s ** np.arange(n)) @ (np.eye(n) - c * np.triu(np.ones((n, n)), 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = analyse(J, _specs(n), tol=1e-12)
    assert len(a.identified) == n and a.condition_number > 1e9
    rhos = np.array([r for _, _, r in a.correlated])
    assert len(rhos) > 0 and np.isfinite(rhos).all() and (np.abs(rhos) <= 1.0).all()
