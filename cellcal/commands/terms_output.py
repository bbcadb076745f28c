"""The lines a calibration prints about its error terms beyond geometry: each term tried,
accepted or not and why, and the accepted terms' coefficients with their uncertainty;
and a campaign's repeated reference poses (repeatability and drift)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # types only: the commands that print a result have it imported already
    from cellcal.calib.calibration_result import CalibrationResult
    from cellcal.calib.reference_repeats import ReferenceRepeat

#: Coefficients shown per term line before "…" (gravity terms have dozens).
SHOWN = 6


def terms_lines(res: CalibrationResult) -> list[str]:
    """Nothing for ``--terms geometric``; else a heading, one line per term, and one per
    fitted term with its coefficients (display units, ± 1σ)."""
    c = res.term_choice
    if c is None:
        return []
    out = [
        f"error terms beyond geometry ({c.mode}): blocked cross-validation RMS "
        f"{c.geometric_cv_mm:.4g} mm geometric, {c.final_cv_mm:.4g} mm final"
    ]
    for v in c.verdicts:
        out.append(f"  {v.name}: {'accepted' if v.accepted else 'not added'} — {v.reason}")
    for t in res.calibrated.terms:
        where = f" joint {t.joint}" if t.joint else f" with {t.variable}"
        parts = [
            f"{r} {t.to_display(k, t.coefficients[k]):+.4g} ± {t.to_display(k, t.sigma[k]):.2g} "
            f"{t.display_unit(k)}"
            for k, r in enumerate(t.regressors)
        ]
        more = f", … ({len(parts) - SHOWN} more)" if len(parts) > SHOWN else ""
        out.append(f"    {t.name}{where}: {', '.join(parts[:SHOWN])}{more}")
    return out


def repeats_text(repeats: tuple[ReferenceRepeat, ...]) -> str:
    """One clause per reference pose: measurements, repeatability, drift ± 1σ."""

    def drift(r: ReferenceRepeat) -> str:
        if math.isnan(r.drift_mm_per_h):
            return "drift not measured"
        return f"drift {r.drift_mm_per_h:.4f} ± {r.drift_sigma_mm_per_h:.4f} mm/h"

    return "; ".join(
        f"{r.label} {r.n}× over {r.hours:.2f} h: repeatability {r.repeatability_mm:.4f} mm "
        f"RMS, {drift(r)}"
        for r in repeats
    )
