"""Blocked cross-validation: how well a fit predicts poses it did not see, where the
unseen poses are a whole region of the workspace, or a later stretch of the campaign.

Random folds flatter a model with many parameters: every left-out pose has neighbours
in the training set, and a term that merely interpolates the noise between them looks
useful. Here a fold is either

* a **region**: the poses are clustered by where the target is (k-means on the nominal
  positions in the base frame, seeded, so the split repeats), and each region is
  predicted by a fit to the others; or
* a **later stretch**: the poses sorted by their time (or temperature) are cut into
  :data:`STRETCHES` equal stretches, and each of the later ones is predicted by a fit
  to all the others — a region of time, the last one beyond every pose the fit saw,
  which is what a drift term claims to predict. (Fitting each stretch from only those
  before it leaves a campaign of a few dozen poses too few to fit the geometry.)

Each fold's fit is a Gauss–Newton step from the fit to all the poses on the other
poses' normal equations (as :func:`cellcal.calib.parameter_choice.kfold_rms` does):
exact to first order, one pass over the poses for every fold. The result is every
tested pose's position error (mm), so that two models can be compared pose by pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.calib import levenberg
from cellcal.calib.error_model import ParameterSpec, State
from cellcal.calib.geometry import Array
from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.observations import Data

#: Regions of the workspace (folds) a calibration's poses are cut into.
REGIONS = 5
#: Stretches of time a campaign is cut into; the later ones are predicted.
STRETCHES = 5
#: A region or stretch needs at least this many poses to be a fold of its own.
MIN_FOLD = 3


@dataclass(frozen=True)
class Folds:
    """``label``: each pose's fold (N); ``train``: for each fold, the folds its fit sees
    (empty: the fold is never predicted, only learnt from); ``kind``: ``regions`` or
    ``stretches``."""

    label: NDArray[np.intp]
    train: tuple[tuple[int, ...], ...]
    kind: str

    @property
    def tested(self) -> NDArray[np.bool_]:
        """The poses that are predicted."""
        out: NDArray[np.bool_] = np.array([bool(self.train[f]) for f in self.label.tolist()])
        return out


def region_folds(state: State, data: Data, regions: int = REGIONS) -> Folds:
    """Poses clustered by their nominal target position (base frame) into regions."""
    model = state.model.geometry
    p = target_kinematics(model, data.q, state.target_offsets[data.groups.target], jacobian=False).p
    k = max(2, min(regions, len(p) // MIN_FOLD))
    from scipy.cluster.vq import kmeans2  # heavy: imported when folds are made

    _, raw = kmeans2(p, k, seed=np.random.default_rng(0), minit="++")
    used = sorted(set(np.asarray(raw).tolist()))
    remap = {v: i for i, v in enumerate(used)}
    label = np.array([remap[v] for v in np.asarray(raw).tolist()], dtype=np.intp)
    n = len(used)
    return Folds(label, tuple(tuple(j for j in range(n) if j != i) for i in range(n)), "regions")


def stretch_folds(order: Array, stretches: int = STRETCHES) -> Folds:
    """Poses sorted by ``order`` (time or temperature) into stretches; each stretch after
    the second is predicted by all the others."""
    n = len(order)
    rank = np.empty(n, dtype=np.intp)
    rank[np.argsort(order, kind="stable")] = np.arange(n)
    label = ((rank * stretches) // max(n, 1)).astype(np.intp)
    train = tuple(
        tuple(k for k in range(stretches) if k != f) if f >= 2 else () for f in range(stretches)
    )
    return Folds(label, train, "stretches")


def held_out_errors(
    state: State, specs: tuple[ParameterSpec, ...], data: Data, w: Array, folds: Folds
) -> Array:
    """Each tested pose's position error (mm; NaN for untested poses) when predicted by
    a fit of ``specs`` to its fold's training poses, starting from ``state`` (a fit to
    all the poses)."""
    fold = folds.label
    F = len(folds.train)
    P = len(specs)
    G = np.zeros((F, P, P))
    g = np.zeros((F, P))
    chunks = range(0, len(data.q), levenberg.CHUNK)
    for start in chunks:
        rows = np.arange(start, min(len(data.q), start + levenberg.CHUNK))
        sub = data.subset(rows)
        r = sub.residuals(state) * w[rows]
        J = sub.jacobian(state, specs) * w[rows][:, :, None]
        for f in range(F):
            mine = fold[rows] == f
            Jw = J[mine].reshape(-1, P)
            G[f] += Jw.T @ Jw
            g[f] += Jw.T @ r[mine].reshape(-1)
    deltas = np.zeros((F, P))
    for f in range(F):
        if not folds.train[f]:
            continue
        train = list(folds.train[f])
        deltas[f] = levenberg.solve_step(
            levenberg.Linearisation(G[train].sum(axis=0), g[train].sum(axis=0), 0.0)
        )
    out = np.full(len(data.q), math.nan)
    predicted = folds.tested
    for start in chunks:
        rows = np.arange(start, min(len(data.q), start + levenberg.CHUNK))
        tested = rows[predicted[rows]]
        if not len(tested):
            continue
        sub = data.subset(tested)
        r = sub.residuals(state)[:, :3]
        J = sub.jacobian(state, specs)[:, :3]
        step = np.einsum("nip,np->ni", J, deltas[folds.label[tested]])
        out[tested] = np.linalg.norm(r - step, axis=1)
    return out


@dataclass(frozen=True)
class Comparison:
    """Two models' held-out errors on the same poses: their RMS (mm), the relative gain
    of the second, and how many standard errors the pose-by-pose gain in squared error
    is from zero (``z``)."""

    before_mm: float
    after_mm: float
    z: float

    @property
    def gain(self) -> float:
        return 1.0 - self.after_mm / self.before_mm if self.before_mm > 0 else 0.0


def compare(before: Array, after: Array) -> Comparison:
    """Compare the held-out errors of two models on the poses both tested."""
    ok = np.isfinite(before) & np.isfinite(after)
    b, a = before[ok] ** 2, after[ok] ** 2
    if not len(b):
        return Comparison(math.nan, math.nan, 0.0)
    d = b - a
    se = float(np.std(d, ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else math.inf
    z = float(np.mean(d)) / se if se > 0 else (math.inf if np.mean(d) > 0 else 0.0)
    return Comparison(math.sqrt(float(np.mean(b))), math.sqrt(float(np.mean(a))), z)
