"""The report's section on error terms beyond geometry: which terms the calibration
tried, accepted or not and why, the blocked cross-validation before and after, and each
accepted term's size, share of the error and coefficients."""

from __future__ import annotations

from typing import Any

from cellcal.calib.term_effect import TermEffect
from cellcal.reports.html_parts import esc, mm_text, table


def _coefficients(term: dict[str, Any]) -> str:
    sigma = term.get("sigma") or [None] * len(term["coefficients"])
    return "; ".join(
        f"{r} {c:+.4g}" + (f" ± {s:.2g}" if s is not None else "") + f" {u}"
        for r, c, s, u in zip(
            term["regressors"], term["coefficients"], sigma, term["units"], strict=True
        )
    )


def terms_section(doc: dict[str, Any], effects: tuple[TermEffect, ...]) -> str:
    """The section, or nothing for a model fitted with ``terms = "geometric"``.

    A term's share of the error is its displacement's mean square at the calibration
    poses over that of every term together plus the fit's residual: the part of what a
    geometric model of these poses could not explain that the term holds."""
    choice = doc.get("fit", {}).get("terms")
    if not isinstance(choice, dict):
        return ""
    cv = choice.get("blocked_cv_mm", {})
    parts = [
        "<h2>Error terms beyond geometry</h2>",
        f"<p>Mode {esc(choice.get('mode'))}: a term is added only when blocked "
        "cross-validation — whole regions of the workspace left out, and for a drift later "
        "stretches of the campaign — says it predicts better. Blocked cross-validation RMS: "
        f"{mm_text(cv.get('geometric'))} mm geometric, {mm_text(cv.get('final'))} mm "
        "with the accepted terms.</p>",
    ]
    rows: list[list[object]] = [[name, "accepted", ""] for name in choice.get("accepted", [])]
    rows += [[name, "not added", why] for name, why in choice.get("rejected", {}).items()]
    parts.append(table(["term", "verdict", "why not"], rows, left=3, ident="terms"))
    if not effects:
        return "".join(parts)
    residual = float(doc["fit"]["rms_after_mm"])
    total = effects[-1].rms_mm ** 2 + residual**2
    sizes = [
        [
            e.name,
            ", ".join(str(j) for j in e.joints) if e.joints != (0,) else "—",
            mm_text(e.rms_mm),
            mm_text(e.max_mm),
            f"{100.0 * e.rms_mm**2 / total:.0f} %" if total > 0 else "—",
        ]
        for e in effects
    ]
    parts.append(
        table(
            ["term", "joints", "RMS mm", "max mm", "share of the error"],
            sizes,
            left=2,
            ident="term-sizes",
        )
    )
    parts.append(
        '<p class="note">Size: how far the term moves the target at the calibration poses '
        "(the model with it against its geometry alone). Share: its mean square over that "
        "of every term together plus the fit's residual.</p>"
    )
    coefficient_rows = [
        [t["name"], t["joint"] or "—", _coefficients(t)] for t in doc.get("term", [])
    ]
    parts.append(
        table(
            ["term", "joint", "coefficients ± 1σ"],
            coefficient_rows,
            left=3,
            ident="term-coefficients",
        )
    )
    return "".join(parts)
