"""The plain fit: a peer for cellcal's identification in the benchmarks.

What anyone with scipy would write: ``scipy.optimize.least_squares`` (``method="lm"``,
scipy's default finite-difference Jacobian, default tolerances, no scaling, no weights)
over the SAME parameters a cellcal calibration identified
(``CalibrationResult.covariance_specs``: kinematic corrections, target offsets, sensor
frames), from cellcal's closed-form start
(:func:`cellcal.calib.observations.initial_state`), residuals measured − predicted in mm.
No identifiability analysis, no noise-hidden parameters left out, no acceptance checks:
the comparison says what cellcal's machinery adds beyond choosing the parameters.

    from plain_fit import plain_fit
    res = calibrate(nominal, q, xyz, groups=g)
    pf = plain_fit(nominal, q, xyz, res.covariance_specs, g)
    pf.predict(q_held_out, g_held_out), pf.seconds, pf.nfev, pf.peak_bytes
"""

from __future__ import annotations

import time
import tracemalloc
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cellcal.calib.error_model import Groups, ParameterSpec, State, apply, predict
from cellcal.calib.geometry import Array
from cellcal.calib.observations import Data, initial_state
from cellcal.calib.robot_model import RobotModel


@dataclass(frozen=True)
class PlainFit:
    """The plain fit's model and cost: ``state`` the fitted geometry, target offsets and
    sensor frames; ``seconds`` the wall time of start plus fit (untraced); ``nfev``
    every evaluation of the residuals, the finite-difference Jacobian's included
    (scipy's own ``nfev`` leaves those out for ``lm`` since 1.16);
    ``peak_bytes`` the peak of Python allocations during a second, traced run;
    ``success``/``message`` scipy's verdict."""

    state: State
    seconds: float
    nfev: int
    peak_bytes: int
    success: bool
    message: str

    def predict(self, q: Array, groups: Groups | None = None) -> Array:
        """Target positions in the sensor frame (mm) for joint readings ``q`` (rad)."""
        return predict(self.state, q, groups)


def _fit(
    nominal: RobotModel,
    q: Array,
    measured: Array,
    specs: tuple[ParameterSpec, ...],
    groups: Groups,
) -> tuple[State, int, bool, str]:
    start = initial_state(nominal, q, measured, groups)
    data = Data(q, measured, groups)

    calls = 0

    def fun(x: Array) -> Array:
        nonlocal calls
        calls += 1
        out: Array = data.residuals(apply(start, specs, x)).ravel()
        return out

    res = least_squares(fun, np.zeros(len(specs)), method="lm")
    return apply(start, specs, res.x), calls, bool(res.success), str(res.message)


def plain_fit(
    nominal: RobotModel,
    q: Array,
    measured: Array,
    specs: tuple[ParameterSpec, ...],
    groups: Groups | None = None,
    *,
    measure_memory: bool = True,
) -> PlainFit:
    """Fit ``specs`` (e.g. a calibration's ``covariance_specs``) to joint readings ``q``
    (N×n, rad) and measured positions (N×3, mm, sensor frame) with ``groups`` (targets,
    sessions; None: one of each); ``measure_memory``: run it a second time, traced, for
    ``peak_bytes`` (else 0). Raises what ``initial_state`` raises (e.g.
    :class:`~cellcal.errors.DegenerateGeometryError` for a session on a line)."""
    q = np.asarray(q, dtype=np.float64)
    measured = np.asarray(measured, dtype=np.float64)
    g = groups if groups is not None else Groups.single(len(q))
    t0 = time.perf_counter()
    state, nfev, success, message = _fit(nominal, q, measured, specs, g)
    seconds = time.perf_counter() - t0
    if not measure_memory:
        return PlainFit(state, seconds, nfev, 0, success, message)
    # Memory in a separate run: tracing every allocation slows the run it traces. The
    # peak above what was allocated before it (a caller may be tracing already).
    outer = tracemalloc.is_tracing()
    if not outer:
        tracemalloc.start()
    tracemalloc.reset_peak()
    before, _ = tracemalloc.get_traced_memory()
    try:
        _fit(nominal, q, measured, specs, g)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        if not outer:
            tracemalloc.stop()
    return PlainFit(state, seconds, nfev, peak - before, success, message)
