"""The robust refit of a calibration: scipy's trust-region reflective least squares
with a robust loss (its reweighting is what it is made for), from the least-squares
solution, over the same parameters."""

from __future__ import annotations

import numpy as np

from cellcal.calib import levenberg
from cellcal.calib.error_model import ParameterSpec, State, apply
from cellcal.calib.geometry import Array
from cellcal.calib.observations import Data
from cellcal.errors import ConvergenceError

ROBUST_LOSSES = ("huber", "soft_l1", "cauchy")


def robust_fit(
    state: State,
    specs: tuple[ParameterSpec, ...],
    data: Data,
    w: Array,
    robust: str,
    f_scale: float,
) -> levenberg.Fit:
    """TRF with a robust loss over ``specs`` from ``state`` (scipy: the loss's
    reweighting is what it is made for)."""
    from scipy.optimize import least_squares  # imported by a robust fit only: slow to load

    def fun(x: Array) -> Array:
        out: Array = (data.residuals(apply(state, specs, x)) * w).ravel()
        return out

    def jac(x: Array) -> Array:
        J = data.jacobian(apply(state, specs, x), specs)
        out: Array = -(J * w[:, :, None]).reshape(-1, len(specs))
        return out

    res = least_squares(
        fun,
        np.zeros(len(specs)),
        jac=jac,
        method="trf",
        loss=robust,
        f_scale=f_scale,
        x_scale="jac",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    if not res.success or not np.all(np.isfinite(res.x)):
        raise ConvergenceError(f"identification did not converge: {res.message}")
    J = np.asarray(res.jac)
    lin = levenberg.Linearisation(J.T @ J, np.zeros(len(specs)), float(2.0 * res.cost))
    return levenberg.Fit(apply(state, specs, res.x), lin, int(res.nfev))
