"""The report page's sections on checks between calibrations: a check's verdict and its
poses' errors, and the control chart of every check of the model since it became valid
(the RMS errors against their limits, and their trend)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

import numpy as np

from cellcal.reports import figures as figs
from cellcal.reports.data import DriftHistory
from cellcal.reports.html_parts import esc, figure_html, mm_text, table
from cellcal.store.validity import CheckRow

#: ok checks needed before a trend is drawn
TREND_MIN = 3


def _when(stamp: str) -> datetime:
    return datetime.fromisoformat(stamp)


def model_name(drift: DriftHistory | None, summary: dict[str, Any] | None = None) -> str:
    """The model a report is about, as the cell knows it: ``model 3 (campaign 7),
    digest …, valid from … until …``."""
    m = drift.model if drift is not None else None
    if m is None:
        if summary is not None and summary.get("model"):
            return f"{summary['model']}, digest {summary.get('model_digest')}"
        return "none recorded"
    until = "current" if m.valid_until is None else f"until {m.valid_until[:19]} ({m.ended_by})"
    return (
        f"model {m.id} (campaign {m.campaign_id}), digest {m.digest}, valid from "
        f"{m.valid_from[:19]}, {until}"
    )


def check_section(s: dict[str, Any], drift: DriftHistory | None) -> str:
    """A check's verdict, the model it compared with, its limits and each pose's error."""
    bad = s["verdict"] != "ok"
    earlier = s.get("earlier_checks_mm")
    rows = [
        ["RMS error", mm_text(s["rms_mm"])],
        ["largest error", mm_text(s["max_mm"])],
        ["warning limit", mm_text(s["warning_mm"])],
        ["recalibration limit", mm_text(s["limit_mm"])],
        ["1σ the model predicts", mm_text(s.get("predicted_mm"))],
        ["1σ its validation measured", mm_text(s.get("validation_mm"))],
        [f"1σ of the first {s.get('earlier_checks', 0)} ok checks", mm_text(earlier)],
    ]
    poses = [[k, mm_text(e)] for k, e in enumerate(s["errors_mm"])]
    return "".join(
        [
            f'<p class="verdict{" bad" if bad else ""}">verdict: {esc(s["verdict"])}</p>',
            f"<p>cause: {esc(s['cause'] or 'no single cause explains the errors')}</p>"
            if bad
            else "",
            f"<p>Compared with {esc(model_name(drift, s))}: {len(s['errors_mm'])} poses "
            f"measured by {esc(s.get('reference_sensor', ''))}, each one's error the measured "
            "position minus the model's prediction at the reached joints (its sensor frame "
            "and target offset, nothing re-registered). The limits are 2 and 3 times "
            "([check] warning_factor, recalibrate_factor) the largest of the three 1σ "
            "estimates below.</p>",
            "<h2>Check, mm</h2>",
            table(["", "mm"], rows, ident="check-figures"),
            "<h3>Each pose's error (plan order)</h3>",
            table(["pose", "error (mm)"], poses, ident="check-poses"),
        ]
    )


def _trend(days: np.ndarray, checks: list[CheckRow]) -> tuple[float, float] | None:
    ok = np.array([c.verdict == "ok" for c in checks], dtype=bool)
    if ok.sum() < TREND_MIN or np.ptp(days[ok]) == 0:
        return None
    slope, intercept = np.polyfit(
        days[ok], [c.rms_mm for c, k in zip(checks, ok, strict=True) if k], 1
    )
    return float(slope), float(intercept)


def history_section(drift: DriftHistory, salt: str, this_campaign: int) -> str:
    """The control chart and the table of every check of the model so far."""
    checks = list(drift.checks)
    head = "<h2>Checks of the model</h2>"
    name = f"<p>The model: {esc(model_name(drift))}.</p>"
    if not checks:
        return head + name + "<p>No check of this model yet (<code>cellcal check</code>).</p>"
    start = _when(drift.model.valid_from) if drift.model is not None else _when(checks[0].created)
    days = np.array([(_when(c.created) - start).total_seconds() / 86400 for c in checks])
    trend = _trend(days, checks)
    mark = next((k for k, c in enumerate(checks) if c.campaign_id == this_campaign), None)
    svg = figs.control_chart(
        days,
        np.array([c.rms_mm for c in checks]),
        np.array([c.warning_mm for c in checks]),
        np.array([c.limit_mm for c in checks]),
        [c.verdict for c in checks],
        trend,
        salt + "drift",
        mark=mark,
    )
    said = f"A trend needs {TREND_MIN} ok checks at different times."
    if trend is not None:  # per 30 days, or per hour over less than two days of checks
        per, unit = (30.0, "30 days") if np.ptp(days) >= 2 else (1 / 24, "hour")
        said = f"Trend of the ok checks: {trend[0] * per:+.4f} mm per {unit}."
    rows = [
        [
            c.campaign_id,
            c.created[:16].replace("T", " "),
            f"{d:.2f}",
            c.verdict,
            mm_text(c.rms_mm),
            mm_text(c.max_mm),
            mm_text(c.warning_mm),
            mm_text(c.limit_mm),
            (c.cause or "").split("; or ")[0],  # the whole sentence: the check's report
        ]
        for c, d in zip(checks, days, strict=True)
    ]
    columns = ["campaign", "time (UTC)", "days", "verdict", "RMS", "max", "warning", "limit"]
    return "".join(
        [
            head,
            name,
            figure_html(svg, f"Each check's RMS error against its limits. {said}", "drift-chart"),
            table([*columns, "cause"], rows, left=1, ident="drift-checks"),
        ]
    )
