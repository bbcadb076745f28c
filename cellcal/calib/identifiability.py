"""Which parameters the measurements can identify, and how well.

The identification Jacobian (measurement weights applied) has its columns scaled to
unit length, so that millimetres and radians compare. Parameters are then chosen group
by group, in order of priority — the instrument frame, then the target offset, then
the kinematic corrections — each group by a column-pivoted QR of its columns with the
directions already chosen projected out. A column whose remaining length is below
``tol`` adds nothing the chosen ones cannot explain: it is not identifiable from these
poses and stays at nominal. This is the "base parameter" selection of FIGAROH and of
Khalil & Dombre, computed from the actual poses rather than assumed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr

from cellcal.calib.error_model import KINEMATIC_KINDS, ParameterSpec
from cellcal.calib.geometry import Array
from cellcal.errors import DegenerateGeometryError

#: Remaining (unit-scaled) column length below which a parameter is not identifiable.
IDENTIFIABLE_TOL = 1e-6
#: Pairs of identified parameters more correlated than this are reported.
CORRELATION_WARN = 0.9


@dataclass(frozen=True)
class Identifiability:
    """``identified``/``unidentifiable``: indices into ``specs``; ``condition_number`` of
    the unit-scaled Jacobian of the identified set; ``correlated``: (name, name, ρ) with
    |ρ| > 0.9; ``remaining``: each parameter's remaining column length when it was
    considered (1 = independent of everything chosen before it, 0 = fully explained)."""

    specs: tuple[ParameterSpec, ...]
    identified: tuple[int, ...]
    unidentifiable: tuple[int, ...]
    condition_number: float
    correlated: tuple[tuple[str, str, float], ...]
    remaining: tuple[float, ...]

    @property
    def identified_names(self) -> tuple[str, ...]:
        return tuple(self.specs[i].name for i in self.identified)

    @property
    def unidentifiable_names(self) -> tuple[str, ...]:
        return tuple(self.specs[i].name for i in self.unidentifiable)


def _groups(specs: Sequence[ParameterSpec]) -> list[list[int]]:
    frame = [i for i, s in enumerate(specs) if s.kind.startswith("frame")]
    tool = [i for i, s in enumerate(specs) if s.kind == "tool"]
    kin = [i for i, s in enumerate(specs) if s.kind in KINEMATIC_KINDS]
    return [g for g in (frame, tool, kin) if g]


def analyse(
    J: Array, specs: tuple[ParameterSpec, ...], *, tol: float = IDENTIFIABLE_TOL
) -> Identifiability:
    """Identifiable subset of ``specs`` for the (M×P) weighted Jacobian ``J``."""
    norms = np.linalg.norm(J, axis=0)
    Js = J / np.where(norms > 0, norms, 1.0)
    M = J.shape[0]
    basis = np.zeros((M, 0))
    chosen: list[int] = []
    remaining = np.zeros(len(specs))
    for group in _groups(specs):
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
                "the measurements do not determine the instrument frame (they lie on a "
                "line or are too few); spread the poses over a volume"
            )
        chosen += [group[int(i)] for i in piv[:k]]
        if k:
            Qk = Qg[:, :k]
            Qk = Qk - basis @ (basis.T @ Qk)  # re-orthogonalise against rounding
            Qk, _ = np.linalg.qr(Qk)
            basis = np.hstack([basis, Qk])
    chosen.sort()
    others = tuple(i for i in range(len(specs)) if i not in set(chosen))
    S = np.linalg.svd(Js[:, chosen], compute_uv=False)
    cond = float(S[0] / S[-1]) if S[-1] > 0 else float("inf")
    correlated: list[tuple[str, str, float]] = []
    try:
        C = np.linalg.inv(Js[:, chosen].T @ Js[:, chosen])
        sd = np.sqrt(np.diag(C))
        rho = C / np.outer(sd, sd)
        ii, jj = np.nonzero(np.triu(np.abs(rho) > CORRELATION_WARN, k=1))
        for a, b in zip(ii, jj, strict=True):
            correlated.append(
                (specs[chosen[a]].name, specs[chosen[b]].name, round(float(rho[a, b]), 4))
            )
    except np.linalg.LinAlgError:
        pass
    return Identifiability(
        specs=specs,
        identified=tuple(chosen),
        unidentifiable=others,
        condition_number=cond,
        correlated=tuple(correlated),
        remaining=tuple(float(r) for r in remaining),
    )
