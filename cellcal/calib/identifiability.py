"""Which parameters the measurements can identify, and how well.

The identification Jacobian (measurement weights applied) has its columns scaled to
unit length, so that millimetres and radians compare. Parameters are then chosen group
by group, in order of priority — the sensor frame, then the target offset, then
the kinematic corrections, then any error terms — each group by a column-pivoted QR of
its columns with the directions already chosen projected out. A column whose remaining
length is below ``tol`` adds nothing the chosen ones cannot explain: it is not
identifiable from these poses and stays at nominal. This is the "base parameter"
selection of FIGAROH and of Khalil & Dombre, computed from the actual poses rather than
assumed.

That test is exact rank, and rank is not enough: a column that is *nearly* a
combination of others passes it, and the fit then "identifies" an absurd value that
happens to absorb noise and unmodelled errors (on a real UR5, α5 −24° and a5 −41 mm).
Identifiability is a matter of degree, set by the singular values a parameter
contributes and by the measurement noise: its standard uncertainty
σ₀·√((JᵀJ)⁻¹)ᵢᵢ. :func:`weakly_determined` leaves at nominal, worst first, every
kinematic parameter and target-offset component whose uncertainty exceeds
:data:`DETERMINED_MM` or :data:`DETERMINED_DEG` — a correction the data cannot tell
from zero to better than a manufacturing tolerance is not worth estimating.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_model import KINEMATIC_KINDS, ParameterSpec
from cellcal.calib.geometry import Array
from cellcal.errors import DegenerateGeometryError

#: Remaining (unit-scaled) column length below which a parameter is not identifiable.
IDENTIFIABLE_TOL = 1e-6
#: Pairs of identified parameters more correlated than this are reported.
CORRELATION_WARN = 0.9
#: A correction is estimated only if the data determine it to within these (1σ).
DETERMINED_MM = 1.0
DETERMINED_DEG = 0.1


@dataclass(frozen=True)
class Identifiability:
    """``identified``/``unidentifiable``: indices into ``specs``; ``condition_number`` of
    the unit-scaled Jacobian of the identified set; ``correlated``: (name, name, ρ) with
    |ρ| > 0.9; ``remaining``: each parameter's remaining column length when it was
    considered (1 = independent of everything chosen before it, 0 = fully explained);
    ``weak``: those left at nominal because the noise hides them (subset of
    ``unidentifiable``), ``fixed``: those pinned by the user."""

    specs: tuple[ParameterSpec, ...]
    identified: tuple[int, ...]
    unidentifiable: tuple[int, ...]
    condition_number: float
    correlated: tuple[tuple[str, str, float], ...]
    remaining: tuple[float, ...]
    weak: tuple[int, ...] = ()
    fixed: tuple[int, ...] = ()

    @property
    def identified_names(self) -> tuple[str, ...]:
        return tuple(self.specs[i].name for i in self.identified)

    @property
    def unidentifiable_names(self) -> tuple[str, ...]:
        return tuple(self.specs[i].name for i in self.unidentifiable)

    def reason(self, index: int) -> str:
        """Why a parameter is at nominal: ``fixed``, ``weak`` or ``rank``."""
        if index in self.fixed:
            return "fixed"
        return "weak" if index in self.weak else "rank"


def _groups(specs: Sequence[ParameterSpec]) -> list[list[int]]:
    frame = [i for i, s in enumerate(specs) if s.kind.startswith("frame")]
    target_offset = [
        i for i, s in enumerate(specs) if s.kind in ("target_offset", "target_rotation")
    ]
    kin = [i for i, s in enumerate(specs) if s.kind in KINEMATIC_KINDS]
    terms = [i for i, s in enumerate(specs) if s.kind == "term"]
    return [g for g in (frame, target_offset, kin, terms) if g]


#: A column shorter than this fraction of the longest is rounding noise (a parameter with
#: no effect, like θ of the last joint with the target on its axis), not a direction.
NEGLIGIBLE_COLUMN = 1e-10


def _unit_columns(J: Array) -> Array:
    """Columns scaled to unit length; negligible ones set to zero (scaling rounding noise
    to unit length would make it look independent of everything)."""
    norms = np.linalg.norm(J, axis=0)
    live = norms > NEGLIGIBLE_COLUMN * max(float(norms.max(initial=0.0)), 1e-300)
    out: Array = np.where(live, J / np.where(live, norms, 1.0), 0.0)
    return out


def analyse(
    J: Array,
    specs: tuple[ParameterSpec, ...],
    *,
    tol: float = IDENTIFIABLE_TOL,
    fixed: frozenset[str] = frozenset(),
) -> Identifiability:
    """Identifiable subset of ``specs`` for the (M×P) weighted Jacobian ``J``; parameters
    named in ``fixed`` are never chosen."""
    from scipy.linalg import qr  # 0.3 s to import: loaded by an analysis, not at start

    Js = _unit_columns(J)
    M = J.shape[0]
    basis = np.zeros((M, 0))
    chosen: list[int] = []
    remaining = np.zeros(len(specs))
    pinned = tuple(i for i, s in enumerate(specs) if s.name in fixed)
    for full in _groups(specs):
        group = [i for i in full if i not in pinned]
        if not group:
            continue
        G = Js[:, group]
        G = G - basis @ (basis.T @ G)
        Qg, Rg, piv = qr(G, mode="economic", pivoting=True)
        d = np.abs(np.diag(Rg))
        rest = np.zeros(len(group))
        rest[: len(d)] = d
        remaining[np.array(group)[piv]] = rest[: len(piv)]
        k = int(np.count_nonzero(d > tol))
        if specs[group[0]].kind.startswith("frame") and k < len(group):
            raise DegenerateGeometryError(
                "the measurements do not determine the sensor frame (they lie on a "
                "line or are too few); spread the poses over a volume"
            )
        chosen += [group[int(i)] for i in piv[:k]]
        if k:
            Qk = Qg[:, :k]
            Qk = Qk - basis @ (basis.T @ Qk)  # re-orthogonalise against rounding
            Qk, _ = np.linalg.qr(Qk)
            basis = np.hstack([basis, Qk])
    chosen.sort()
    return _conditioned(Js, specs, chosen, tuple(float(r) for r in remaining), (), pinned)


def condition_number(J: Array, columns: Sequence[int]) -> float:
    """The condition number of the (M×P) Jacobian ``J``'s ``columns``, each scaled to unit
    length (as :func:`analyse` reports it)."""
    S = np.linalg.svd(_unit_columns(J)[:, list(columns)], compute_uv=False)
    return float(S[0] / S[-1]) if len(S) and S[-1] > 0 else float("inf")


def _conditioned(
    Js: Array,
    specs: tuple[ParameterSpec, ...],
    chosen: list[int],
    remaining: tuple[float, ...],
    weak: tuple[int, ...],
    fixed: tuple[int, ...],
) -> Identifiability:
    """The Identifiability of the set ``chosen``: its condition number and correlations."""
    others = tuple(i for i in range(len(specs)) if i not in set(chosen))
    # the singular values and right vectors of J are those of R in J = QR: no M×P factor
    _, S, Vt = np.linalg.svd(np.linalg.qr(Js[:, chosen], mode="r"), full_matrices=False)
    cond = float(S[0] / S[-1]) if S[-1] > 0 else float("inf")
    correlated: list[tuple[str, str, float]] = []
    if np.isfinite(cond):
        # (JᵀJ)⁻¹ = V S⁻² Vᵀ: positive definite however ill-conditioned J is, where
        # inverting JᵀJ can leave a negative variance and no correlation at all
        with np.errstate(over="ignore", invalid="ignore"):  # S⁻² beyond float: no ρ
            C = (Vt.T / S**2) @ Vt
            sd = np.sqrt(np.diag(C))
            rho = C / np.outer(sd, sd)
        ii, jj = np.nonzero(np.triu(np.abs(rho) > CORRELATION_WARN, k=1))
        for a, b in zip(ii, jj, strict=True):
            correlated.append(
                (specs[chosen[a]].name, specs[chosen[b]].name, round(float(rho[a, b]), 4))
            )
    return Identifiability(
        specs=specs,
        identified=tuple(chosen),
        unidentifiable=others,
        condition_number=cond,
        correlated=tuple(correlated),
        remaining=remaining,
        weak=weak,
        fixed=fixed,
    )


def _limit(spec: ParameterSpec) -> float:
    """The uncertainty (internal units: mm, rad) beyond which a parameter is weak; an
    error term's joint turn (rad per regressor unit) as an angle — a ratio's too, as the
    turn a radian from its mean reading — a drift never."""
    if spec.kind == "term":
        turns = spec.unit.startswith("deg") or spec.unit == "%"
        return math.radians(DETERMINED_DEG) if turns else math.inf
    return math.radians(DETERMINED_DEG) if spec.is_angle else DETERMINED_MM


def weakly_determined(
    J: Array, sigma0: float, ident: Identifiability, spare: Sequence[int] = ()
) -> Identifiability:
    """``ident`` with every kinematic or target-offset parameter whose standard
    uncertainty σ₀·√((JᵀJ)⁻¹)ᵢᵢ exceeds its limit moved to nominal, worst first (dropping
    one lowers the others' uncertainty). ``J``: the weighted Jacobian at the solution, or
    its R factor, over the columns ``ident.identified`` in that order; ``sigma0``: the
    a-posteriori noise (weighted); ``spare``: indices never left out."""
    specs = ident.specs
    full = np.zeros((J.shape[0], len(specs)))
    full[:, list(ident.identified)] = J
    J = full
    keep = list(ident.identified)
    weak: list[int] = []
    while keep:
        A = J[:, keep]
        try:
            C = np.linalg.inv(A.T @ A) * sigma0**2
        except np.linalg.LinAlgError:
            C = np.full((len(keep), len(keep)), np.inf)
        std = np.sqrt(np.clip(np.diag(C), 0.0, None))
        ratio = np.array(
            [
                std[k] / _limit(specs[i])
                if not specs[i].kind.startswith("frame")
                and specs[i].kind != "target_rotation"
                and i not in spare
                else 0.0
                for k, i in enumerate(keep)
            ]
        )
        worst = int(np.argmax(ratio))
        if not ratio[worst] > 1.0:
            break
        weak.append(keep.pop(worst))
    if not weak:
        return ident
    return _conditioned(_unit_columns(J), specs, keep, ident.remaining, tuple(weak), ident.fixed)
