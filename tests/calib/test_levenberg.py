"""cellcal's Levenberg–Marquardt (cellcal.calib.levenberg) against scipy's, and its
pose-by-pose normal equations."""

from __future__ import annotations

import tracemalloc

import numpy as np

from cellcal.calib import levenberg
from cellcal.calib.error_model import Groups, apply, parameter_specs
from cellcal.calib.identifiability import analyse
from cellcal.calib.observations import Data, initial_state
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import measure, random_cell, random_joints
from tests.lazy import least_squares

KR5 = load_model("kuka-kr5-arc").model


def _problem(n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    cell = random_cell(KR5, rng)
    q = random_joints(KR5, rng, n)
    m = measure(cell, q, rng, 0.01)
    g = Groups.single(n)
    data = Data(q, m, g)
    start = initial_state(KR5, q, m, g)
    specs = parameter_specs(KR5, groups=g)
    w = np.ones((n, 3))
    ident = analyse(levenberg.linearise(start, specs, data, w).R, specs)
    sel = tuple(specs[i] for i in ident.identified)
    return data, start, sel, w


def test_chunks_add_up_to_the_whole():
    data, start, sel, w = _problem(300)
    whole = levenberg.linearise(start, sel, data, w, chunk=10_000)
    parts = levenberg.linearise(start, sel, data, w, chunk=7)
    np.testing.assert_allclose(parts.G, whole.G, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(parts.g, whole.g, rtol=1e-10, atol=1e-9)
    assert abs(parts.cost - whole.cost) <= 1e-10 * whole.cost
    R = whole.R
    np.testing.assert_allclose(R.T @ R, whole.G, rtol=1e-8, atol=1e-8 * np.abs(whole.G).max())


def test_the_fit_reaches_scipys_minimum():
    data, start, sel, w = _problem(200)
    mine = levenberg.fit(start, sel, data, w)

    def fun(x):
        return data.residuals(apply(start, sel, x)).ravel()

    def jac(x):
        return -data.jacobian(apply(start, sel, x), sel).reshape(-1, len(sel))

    ref = least_squares(fun, np.zeros(len(sel)), jac=jac, method="lm", xtol=1e-14, ftol=1e-14)
    assert mine.lin.cost <= 2 * ref.cost * (1 + 1e-9)
    # the same state: predicted positions agree far below the noise (0.01 mm)
    theirs = apply(start, sel, ref.x)
    diff = data.residuals(mine.state) - data.residuals(theirs)
    assert np.abs(diff).max() < 1e-6
    assert mine.passes <= 6


def test_memory_does_not_grow_with_the_poses():
    """Only JᵀJ is kept: a pass over 20 000 poses needs about what one chunk needs."""

    def peak(n: int) -> int:
        data, start, sel, w = _problem(n, seed=2)
        tracemalloc.start()
        try:
            levenberg.linearise(start, sel, data, w, chunk=1024)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    small, large = peak(2048), peak(20_000)
    assert large < 1.5 * small
