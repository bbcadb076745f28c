"""The fleet's page across cells (``cellcal fleet report``): each robot's current model
and its age, its checks — the last verdict, the drift of its RMS error against its limit
and its trend, when the next check is due —, and its calibrations' accuracy before and
after, grouped by line; one self-contained ``index.html`` and ``fleet.json``.

A row's small chart (a cell's checks of its current model — without one, of the model
the last check ended —, RMS over its recalibration limit) is an SVG polyline written
here: two hundred matplotlib figures would take seconds, one polyline takes
microseconds. The overview figure is matplotlib's."""

from __future__ import annotations

import io
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from cellcal.reports.html_parts import esc, mm_text, table
from cellcal.store.fleet_queries import FleetCheck, FleetData, FleetModel

#: a check is "due" this long before its time
DUE_AHEAD = timedelta(days=1)
#: ok checks needed for a trend
TREND_MIN = 3
STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:80em;color:#222;padding:0 1em}
h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.6em 0}td,th{padding:.2em .6em;border-bottom:1px solid #eee;
text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}th{background:#f4f4f4;
white-space:normal}td.l,th.l{text-align:left}td.w{white-space:normal}
.overdue,.recalibrate,.no-model{color:#b00;font-weight:600}.due,.warning{color:#a60}
svg{max-width:100%;height:auto}
"""


def _when(stamp: str | datetime) -> datetime:
    return stamp if isinstance(stamp, datetime) else datetime.fromisoformat(stamp)


@dataclass(frozen=True)
class CellRow:
    """What the page shows of one cell."""

    cell: str
    line: str | None
    last_seen: datetime
    model: FleetModel | None
    model_age_days: float | None
    # of the current model, oldest first; without one, those of the model the last check
    # compared with (the check that ended it: the page's most urgent news)
    checks: tuple[FleetCheck, ...]
    due: str  # ok, due, overdue, no model
    next_due: datetime | None
    trend_mm_per_30d: float | None
    calibrations: tuple[tuple[int, str | None, float | None, float | None], ...]

    def as_dict(self) -> dict[str, Any]:
        last = self.checks[-1] if self.checks else None
        return {
            "cell": self.cell,
            "line": self.line,
            "last_seen": self.last_seen.isoformat(),
            "model": None
            if self.model is None
            else {
                "id": self.model.id,
                "campaign_id": self.model.campaign_id,
                "valid_from": self.model.valid_from,
                "digest": self.model.digest,
                "age_days": self.model_age_days,
            },
            "checks": len(self.checks),
            "last_check": None
            if last is None
            else {
                "campaign_id": last.campaign_id,
                "created": last.created,
                "verdict": last.verdict,
                "rms_mm": last.rms_mm,
                "limit_mm": last.limit_mm,
                "cause": last.cause,
            },
            "due": self.due,
            "next_due": None if self.next_due is None else self.next_due.isoformat(),
            "trend_mm_per_30d": self.trend_mm_per_30d,
            "calibrations": [
                {"campaign_id": c, "finished": f, "before_mm": b, "after_mm": a}
                for c, f, b, a in self.calibrations
            ],
        }


def cell_rows(data: FleetData, every: timedelta) -> list[CellRow]:
    """Each cell's row: its current model, its checks, when the next one is due."""
    models = {m.cell: m for m in data.models}
    out = []
    for c in data.cells:
        model = models.get(c.cell)
        mine = [k for k in data.checks if k.cell == c.cell]
        of = model.id if model is not None else mine[-1].model_id if mine else None
        checks = tuple(k for k in mine if k.model_id == of)
        calibrations = tuple(
            (k.campaign_id, k.finished, k.before_mm, k.after_mm)
            for k in data.calibrations
            if k.cell == c.cell
        )
        if model is None:
            out.append(CellRow(c.cell, c.line, c.last_seen, None, None, checks, "no model",
                               None, None, calibrations))  # fmt: skip
            continue
        since = _when(model.valid_from)
        age = (data.now - since).total_seconds() / 86400
        last = _when(checks[-1].created) if checks else since
        next_due = last + every
        due = (
            "overdue" if data.now > next_due else "due" if data.now > next_due - DUE_AHEAD else "ok"
        )
        out.append(
            CellRow(
                c.cell,
                c.line,
                c.last_seen,
                model,
                age,
                checks,
                due,
                next_due,
                _trend(checks, since),
                calibrations,
            )
        )
    return out


def _trend(checks: tuple[FleetCheck, ...], since: datetime) -> float | None:
    ok = [k for k in checks if k.verdict == "ok"]
    days = np.array([(_when(k.created) - since).total_seconds() / 86400 for k in ok])
    if len(ok) < TREND_MIN or np.ptp(days) == 0:
        return None
    slope = np.polyfit(days, [k.rms_mm for k in ok], 1)[0]
    return float(slope * 30)


def sparkline(checks: tuple[FleetCheck, ...], width: int = 120, height: int = 24) -> str:
    """A cell's checks as a polyline: each one's RMS over its recalibration limit (the
    dashed line is the limit, 1)."""
    if not checks:
        return ""
    ratios = np.array([k.rms_mm / k.limit_mm if k.limit_mm > 0 else np.nan for k in checks])
    top = max(1.2, float(np.nanmax(ratios)) if np.isfinite(ratios).any() else 1.2)
    x = np.linspace(2, width - 2, len(ratios)) if len(ratios) > 1 else np.array([width / 2])
    y = height - 2 - (height - 4) * np.nan_to_num(ratios) / top
    limit = height - 2 - (height - 4) / top
    points = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(x, y, strict=True))
    colour = "#b00" if checks[-1].verdict == "recalibrate" else "#2e75b6"
    dots = "".join(
        f'<circle cx="{a:.1f}" cy="{b:.1f}" r="1.8"/>' for a, b in zip(x, y, strict=True)
    )
    return (
        f'<svg width="{width}" height="{height}" viewBox="0 0 {width} {height}" role="img">'
        f'<line x1="0" x2="{width}" y1="{limit:.1f}" y2="{limit:.1f}" stroke="#c0504d" '
        f'stroke-dasharray="3,2" stroke-width="1"/>'
        f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{points}"/>'
        f'<g fill="{colour}">{dots}</g></svg>'
    )


def overview_svg(rows: list[CellRow]) -> str:
    """Every cell's last check, its RMS over its recalibration limit, worst first."""
    shown = [(r.cell, r.checks[-1]) for r in rows if r.checks]
    if not shown:
        return ""
    shown.sort(key=lambda s: -s[1].rms_mm / s[1].limit_mm)
    fig = Figure(figsize=(9.0, 3.0), dpi=100)
    fig.set_layout_engine("constrained")
    ax = fig.add_subplot()
    ratio = [k.rms_mm / k.limit_mm for _, k in shown]
    colours = {"ok": "#2e75b6", "warning": "#d08c00", "recalibrate": "#c0504d"}
    ax.bar(range(len(shown)), ratio, color=[colours.get(k.verdict, "#777") for _, k in shown])
    ax.axhline(1.0, color="#c0504d", lw=1, label="recalibration limit")
    ax.set_ylabel("last check RMS / limit")
    ax.set_xlabel(f"{len(shown)} cells, worst first")
    if len(shown) <= 40:
        ax.set_xticks(range(len(shown)), [c for c, _ in shown], rotation=90, fontsize=7)
    else:
        ax.set_xticks([])
    ax.legend(frameon=False, fontsize=8)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return text[text.index("<svg") :]


def _cls(value: str) -> str:
    return value.replace(" ", "-")


def _td(text: str, cls: str = "") -> str:
    return f'<td class="{cls}">{text}</td>' if cls else f"<td>{text}</td>"


def _cells(r: CellRow) -> list[str]:
    """One cell's row of the table, as HTML cells."""
    out = [_td(esc(r.cell), "l")]
    if r.model is not None and r.model_age_days is not None:
        out += [_td(f"{r.model.id} ({esc(r.model.digest)})", "w"), _td(f"{r.model_age_days:.1f}")]
    else:
        out += [_td("none", "no-model"), _td("—")]
    out.append(_td(str(len(r.checks))))
    last = r.checks[-1] if r.checks else None
    if last is not None:
        out += [
            _td(esc(last.created[:16].replace("T", " "))),
            _td(esc(last.verdict), _cls(last.verdict)),
            _td(f"{mm_text(last.rms_mm)} / {mm_text(last.limit_mm)}"),
        ]
    else:
        out += [_td("—")] * 3
    out += [_td(sparkline(r.checks)), _td(mm_text(r.trend_mm_per_30d))]
    when = f"{r.due}, {r.next_due:%Y-%m-%d}" if r.next_due is not None else r.due
    out.append(_td(esc(when), _cls(r.due)))
    cal = r.calibrations[-1] if r.calibrations else None
    out.append(
        _td(f"{mm_text(cal[2])} → {mm_text(cal[3])} (campaign {cal[0]})", "w") if cal else _td("—")
    )
    return out


def fleet_html(rows: list[CellRow], data: FleetData, server: str, every: timedelta) -> str:
    """The whole page."""
    lines = sorted({r.line or "" for r in rows})
    due = sum(r.due in ("due", "overdue", "no model") for r in rows)
    parts = [
        "<h1>cellcal fleet</h1>",
        f"<p>{len(rows)} cells on {esc(server)}, {data.now:%Y-%m-%d %H:%M} UTC; a check is due "
        f"every {every.days:g} days after the last one (or the model's calibration); "
        f"{due} of them need{'s' if due == 1 else ''} a check or a calibration now.</p>",
        overview_svg(rows),
    ]
    head = [
        "cell", "model", "age (d)", "checks", "last check", "verdict", "RMS / limit (mm)",
        "drift", "trend (mm/30 d)", "next check", "last calibration (mm, before → after)",
    ]  # fmt: skip
    for line in lines:
        mine = [r for r in rows if (r.line or "") == line]
        parts.append(f"<h2>{esc(line or 'cells without a line')}</h2>")
        body = "".join("<tr>" + "".join(_cells(r)) + "</tr>" for r in mine)
        heads = "".join(f"<th>{esc(h)}</th>" for h in head)
        parts.append(f"<table><tr>{heads}</tr>{body}</table>")
    calibrations = [
        [r.cell, c, (f or "")[:16].replace("T", " "), mm_text(b), mm_text(a)]
        for r in rows
        for c, f, b, a in r.calibrations
    ]
    parts += [
        "<h2>Calibrations: validation RMS before and after (mm)</h2>",
        table(
            ["cell", "campaign", "finished (UTC)", "before", "after"],
            calibrations,
            ident="calibrations",
        ),
    ]
    return (
        '<!doctype html><html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width"><title>cellcal fleet</title>'
        f"<style>{STYLE}</style></head><body>" + "".join(parts) + "</body></html>\n"
    )
