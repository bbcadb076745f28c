"""Levenberg–Marquardt on the normal equations of the weighted Jacobian, built pose by pose.

Why not ``scipy.optimize.least_squares``: it asks for the residuals and the Jacobian in
separate calls (two forward-kinematics passes where one gives both), holds the whole
3N×P Jacobian (and MINPACK a copy of it), and stops on rules in units of the parameters,
not of their uncertainty. Here each pass over the poses gives, chunk by chunk, the
residuals and the Jacobian together and folds them into JᵀJ and Jᵀr (P×P and P); only
those are kept, so memory does not grow with the number of poses. Every column-space
question — the step, identifiability, the covariance (JᵀJ)⁻¹ — is answered from JᵀJ:
:attr:`Linearisation.R` is a square root of it, with the same singular values and column
geometry as J. The columns are scaled to unit length before JᵀJ is formed, so squaring
the condition number costs digits only beyond a condition of about 10⁷, far past where
:mod:`cellcal.calib.identifiability` has already refused the parameter. (A QR of each
chunk would keep those digits, but LAPACK's threaded QR of a tall, thin matrix is ten
times slower than the product on two cores, and the product is what BLAS does best.)

The iteration stops when the Gauss–Newton step left is below :data:`STEP_TOL` of the
parameters' standard uncertainty: √(gᵀ(JᵀJ)⁻¹g) with g = Jᵀr is that step's length in
units of the a-posteriori σ₀, so no further pass could move an estimate by a visible
fraction of its uncertainty. Near-linear problems from a closed-form start (this one's)
stop after three or four passes.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ParamSpec, TypeVar

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController  # type: ignore[import-untyped]

from cellcal.calib.error_model import ParameterSpec, State, apply
from cellcal.calib.geometry import Array
from cellcal.calib.observations import Data
from cellcal.errors import ConvergenceError

#: Poses per chunk: large enough for numpy to run at full speed, small enough that a
#: chunk's Jacobian (and the kinematics behind it) stays a few MB at any campaign size.
CHUNK = 2048
#: Stop when the remaining Gauss–Newton step is this fraction of a standard uncertainty.
STEP_TOL = 1e-3
#: A looser stop, and a budget of passes, for a fit whose estimates serve only to judge
#: which parameters to keep (σ₀ and the Jacobian there change little after a few passes).
COARSE = 0.1
COARSE_PASSES = 6
#: Passes allowed per parameter (MINPACK's default budget: a curved valley, as an
#: over-parameterised real robot has, can take a few hundred).
PASSES_PER_PARAMETER = 100
#: Relative change of the cost that is rounding, not a change.
ROUNDING = 1e-12
#: Damping (relative to the unit-scaled JᵀJ) of the first step, and its least value.
DAMPING_START = 1e-6
DAMPING_MIN = 1e-12
#: Damping beyond which no step decreases the cost any more: the cost is at its floor.
DAMPING_FLOOR = 1e12
#: A step that lowers the cost by less than this fraction of it changed nothing.
STAGNANT = 1e-10


_P = ParamSpec("_P")
_T = TypeVar("_T")
_controller: list[ThreadpoolController] = []


def one_blas_thread(fn: Callable[_P, _T]) -> Callable[_P, _T]:
    """Run ``fn`` with BLAS on one thread. The products here are tall and thin (3N×P,
    P ≈ 30): a second thread saves little, and on a busy machine OpenBLAS's threads wait
    for a core — the same fit took 5 ms on one thread and 20 ms to 1.8 s on two with the
    other core loaded."""

    @functools.wraps(fn)
    def run(*args: _P.args, **kwargs: _P.kwargs) -> _T:
        if not _controller:
            _controller.append(ThreadpoolController())
        with _controller[0].limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return run


@dataclass(frozen=True)
class Linearisation:
    """The weighted least-squares problem at a state, linearised: ``G`` = JᵀJ (P×P) and
    ``g`` = Jᵀr (P) for the weighted Jacobian J = ∂(predicted)/∂(parameters) and the
    weighted residuals r = measured − predicted; ``cost`` = ‖r‖²."""

    G: Array
    g: Array
    cost: float

    @property
    def scale(self) -> Array:
        """The Jacobian's column lengths (1 for a zero column)."""
        d = np.sqrt(np.clip(np.diag(self.G), 0.0, None))
        out: Array = np.where(d > 0, d, 1.0)
        return out

    @property
    def R(self) -> Array:
        """A square root of JᵀJ (RᵀR = JᵀJ): the column geometry of J in P rows."""
        d = self.scale
        # the SVD of a symmetric PSD matrix is its eigen-decomposition (LAPACK's threaded
        # eigh is a hundred times slower at this size on a busy machine)
        _, lam, Vt = np.linalg.svd(self.G / np.outer(d, d))
        out: Array = (np.sqrt(lam)[:, None] * Vt) * d
        return out

    def subset(self, columns: list[int]) -> Linearisation:
        """The same problem over some of its parameters (the others held)."""
        return Linearisation(self.G[np.ix_(columns, columns)], self.g[columns], self.cost)


def linearise(
    state: State, specs: tuple[ParameterSpec, ...], data: Data, w: Array, chunk: int = CHUNK
) -> Linearisation:
    """One pass over the poses: JᵀJ, Jᵀr and ‖r‖² (weighted) at ``state``."""
    return linearise_folds(state, specs, data, w, 1, chunk)[0]


def linearise_folds(
    state: State,
    specs: tuple[ParameterSpec, ...],
    data: Data,
    w: Array,
    folds: int,
    chunk: int = CHUNK,
    labels: NDArray[np.intp] | None = None,
) -> list[Linearisation]:
    """One pass over the poses, its sums kept apart per fold (pose i in fold
    ``labels[i]``, or i mod ``folds``): the whole problem's are their sums."""
    P = len(specs)
    N = len(data.q)
    G = np.zeros((folds, P, P))
    g = np.zeros((folds, P))
    cost = np.zeros(folds)
    for start in range(0, N, chunk):
        rows = np.arange(start, min(N, start + chunk))
        sub = data.subset(rows) if chunk < N else data
        m, J = sub.jacobian_and_positions(state, specs)
        r = sub.measured - m if sub.orientations is None else sub.residuals(state)
        ww = w[rows]
        r *= ww
        J *= ww[:, :, None]
        for k in range(folds):
            if folds == 1:
                mine: slice | NDArray[np.bool_] = slice(None)
            else:
                mine = (rows % folds if labels is None else labels[rows]) == k
            Jw = J[mine].reshape(-1, P)
            rw = r[mine].reshape(-1)
            G[k] += Jw.T @ Jw
            g[k] += Jw.T @ rw
            cost[k] += float(rw @ rw)
    return [Linearisation(G[k], g[k], float(cost[k])) for k in range(folds)]


def _solve(lin: Linearisation, scale: Array, damping: float) -> Array:
    """argmin ‖Jδ − r‖² + damping·‖diag(scale)·δ‖², in unit-scaled columns."""
    d = lin.scale
    A = lin.G / np.outer(d, d) + damping * np.diag((scale / d) ** 2)
    try:
        x = np.linalg.solve(A, lin.g / d)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(A, lin.g / d, rcond=None)[0]
    out: Array = x / d
    return out


def solve_step(lin: Linearisation) -> Array:
    """The Gauss–Newton step: argmin ‖Jδ − r‖²."""
    return _solve(lin, lin.scale, 0.0)


def remaining_step(lin: Linearisation) -> float:
    """√(gᵀ(JᵀJ)⁻¹g): the length of the Gauss–Newton step left, in units of σ₀·σ₀."""
    delta = _solve(lin, lin.scale, 0.0)
    return math.sqrt(max(float(lin.g @ delta), 0.0))


@dataclass(frozen=True)
class Fit:
    """The fitted state, its linearisation there, and the passes over the poses spent."""

    state: State
    lin: Linearisation
    passes: int


def fit(
    state: State,
    specs: tuple[ParameterSpec, ...],
    data: Data,
    w: Array,
    start: Linearisation | None = None,
    tol: float = STEP_TOL,
    limit: int | None = None,
) -> Fit:
    """Levenberg–Marquardt over ``specs`` from ``state`` (weighted least squares);
    ``start``: the problem already linearised at ``state``, if it is at hand; ``tol``:
    the remaining step, in standard uncertainties, at which to stop; ``limit``: passes
    after which to return where the fit has got to (without it, running out of passes
    is a ConvergenceError)."""
    P = len(specs)
    lin = start if start is not None else linearise(state, specs, data, w)
    passes = 0 if start is not None else 1
    if P == 0:
        return Fit(state, lin, passes)
    dof = max(w.size - P, 1)
    scale = lin.scale
    # Nielsen's damping: shrink it as far as the step's actual gain matches the
    # predicted one, grow it ever faster while steps fail (no ×10/÷10 oscillation).
    damping, grow = DAMPING_START, 2.0
    budget = PASSES_PER_PARAMETER * (P + 1) if limit is None else limit
    while passes < budget:
        sigma0 = math.sqrt(lin.cost / dof)
        if not remaining_step(lin) > tol * sigma0:
            return Fit(state, lin, passes)
        delta = _solve(lin, scale, damping)
        predicted = float(2.0 * delta @ lin.g - delta @ lin.G @ delta)
        trial = apply(state, specs, delta)
        new = linearise(trial, specs, data, w)
        passes += 1
        gained = lin.cost - new.cost
        if math.isfinite(new.cost) and gained >= -ROUNDING * lin.cost:
            state, lin = trial, new
            scale = np.maximum(scale, lin.scale)
            if gained <= STAGNANT * new.cost:
                return Fit(state, lin, passes)  # the cost is at its floor (rounding)
            rho = gained / predicted if predicted > 0 else 0.0
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            damping, grow = max(damping, DAMPING_MIN), 2.0
        else:
            damping, grow = damping * grow, grow * 2.0
            if damping > DAMPING_FLOOR:
                return Fit(state, lin, passes)  # no step lowers the cost: at its floor
    if limit is not None:
        return Fit(state, lin, passes)
    raise ConvergenceError(f"identification did not converge within {budget} passes over the poses")
