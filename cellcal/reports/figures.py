"""The report's figures, drawn with matplotlib into inline SVG text.

Only matplotlib's object API is used (``Figure``, no pyplot): no global state, no GUI
backend, safe in the service's worker thread. Text stays text in the SVG (searchable,
small), and the ids are salted with the campaign so that two figures of one page never
share one.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib as mpl
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

from cellcal.calib.geometry import Array
from cellcal.reports.data import (
    MethodComparison,
    PoseAgreement,
    SensorResiduals,
    ValidationPoses,
)

BEFORE, AFTER, PAPER = "#c0504d", "#2e75b6", "#7f7f7f"


def _svg(fig: Figure, salt: str) -> str:
    buf = io.StringIO()
    with mpl.rc_context({"svg.fonttype": "none", "svg.hashsalt": salt}):
        fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return text[text.index("<svg") :]


def _figure(width: float = 7.0, height: float = 3.0) -> Figure:
    fig = Figure(figsize=(width, height), dpi=100)
    fig.set_layout_engine("constrained")
    return fig


def _log_y(ax: Axes, subs: tuple[float, ...] = (1.0, 2.0, 5.0)) -> None:
    """A logarithmic y axis labelled in plain numbers (0.01, 0.02, 0.05, …) at ``subs`` of
    each decade. matplotlib's default labels (10⁻²) are typeset as mathtext, which took
    half of each such figure's time."""
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(subs=subs))
    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _norms(e: Array) -> Array:
    out: Array = np.linalg.norm(e, axis=1)
    return out


def registration_residuals(r: SensorResiduals, salt: str) -> str:
    """The paper's Figs 5 and 6: the registration's residual at each common point (the
    calibration poses), with the nominal geometry and with the calibrated one."""
    fig = _figure()
    ax = fig.add_subplot()
    x = np.arange(len(r.idx))
    ax.plot(x, _norms(r.nominal), "o-", ms=3, lw=0.8, color=BEFORE, label="nominal geometry")
    ax.plot(x, _norms(r.calibrated), "o-", ms=3, lw=0.8, color=AFTER, label="calibrated geometry")
    ax.set_xlabel("calibration pose (in plan order)")
    ax.set_ylabel("residual (mm)")
    ax.set_title(f"{r.sensor}: registration residual per pose")
    ax.legend(frameon=False)
    ax.grid(alpha=0.3)
    return _svg(fig, f"{salt}-reg-{r.sensor}")


def agreement(a: PoseAgreement, reference: str, salt: str) -> str:
    """One sensor's estimate of the reference point against the reference's, per pose."""
    fig = _figure(7.0, 2.6)
    ax = fig.add_subplot()
    ax.plot(np.arange(len(a.idx)), a.distance_mm, "o", ms=3, color=AFTER)
    ax.set_xlabel("pose both measured (in plan order)")
    ax.set_ylabel("distance (mm)")
    ax.set_title(f"{a.sensor} against {reference}, after registration")
    ax.grid(alpha=0.3)
    return _svg(fig, f"{salt}-agree-{a.sensor}")


def validation_errors(v: ValidationPoses, paper: dict[str, float], salt: str) -> str:
    """The paper's Fig. 8: the position error at each validation pose before and after
    calibration, with the paper's averages for scale."""
    fig = _figure(7.5, 3.2)
    ax = fig.add_subplot()
    x = np.arange(len(v.idx))
    ax.plot(x, _norms(v.before), "o-", ms=3, lw=0.8, color=BEFORE, label="before (nominal)")
    ax.plot(x, _norms(v.after), "o-", ms=3, lw=0.8, color=AFTER, label="after (calibrated)")
    ax.axhline(paper["cl_inside_mm"], color=PAPER, ls="--", lw=0.8, label="paper δ₂, inside")
    ax.axhline(paper["other_method_mm"], color=PAPER, ls=":", lw=0.8, label="paper δ₁")
    # Region boundaries, labelled.
    regions = list(v.region)
    for k in range(1, len(regions)):
        if regions[k] != regions[k - 1]:
            ax.axvline(k - 0.5, color="#bbbbbb", lw=0.6)
    for name in dict.fromkeys(regions):
        ks = [k for k, r in enumerate(regions) if r == name]
        ax.text(
            float(np.mean(ks)),
            1.0,
            name,
            transform=ax.get_xaxis_transform(),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    _log_y(ax)
    ax.set_xlabel("validation pose")
    ax.set_ylabel("position error (mm)")
    ax.legend(frameon=False, fontsize=8, ncols=2)
    ax.grid(alpha=0.3, which="both")
    return _svg(fig, f"{salt}-validation")


def region_rms(
    names: Sequence[str],
    before: Sequence[float],
    after: Sequence[float],
    paper: Sequence[float | None],
    salt: str,
) -> str:
    """The paper's Table 3 as bars: RMS per region, before and after, and the paper's."""
    fig = _figure(7.0, 3.0)
    ax = fig.add_subplot()
    x = np.arange(len(names))
    w = 0.28
    ax.bar(x - w, before, w, color=BEFORE, label="before")
    ax.bar(x, after, w, color=AFTER, label="after")
    ax.bar(
        x + w, [p if p is not None else 0.0 for p in paper], w, color=PAPER, label="paper (after)"
    )
    ax.set_xticks(x, list(names))
    ax.set_ylabel("RMS position error (mm)")
    _log_y(ax)
    ax.legend(frameon=False, fontsize=8)
    ax.grid(alpha=0.3, axis="y", which="both")
    return _svg(fig, f"{salt}-regions")


def singular_values(s: Array, salt: str) -> str:
    fig = _figure(7.0, 2.6)
    ax = fig.add_subplot()
    ax.plot(np.arange(1, len(s) + 1), s / s[0], "o-", ms=4, color=AFTER)
    _log_y(ax, subs=(1.0,) if s[-1] < 0.01 * s[0] else (1.0, 2.0, 5.0))  # labels ≥ 2
    ax.set_xlabel("singular value (largest first)")
    ax.set_ylabel("relative to the largest")
    cond = s[0] / s[-1] if s[-1] > 0 else float("inf")
    ax.set_title(f"identification Jacobian (weighted, unit columns): condition number {cond:.3g}")
    ax.grid(alpha=0.3, which="both")
    return _svg(fig, f"{salt}-sv")


def residuals_3d(positions: Array, errors: Array, salt: str) -> str:
    """The calibration poses where they are (base frame), coloured by the fit residual."""
    fig = _figure(6.0, 4.8)
    ax = fig.add_subplot(projection="3d")
    sc = ax.scatter(
        positions[:, 0],
        positions[:, 1],
        positions[:, 2],
        c=errors,
        cmap="viridis",
        s=18,
        depthshade=False,
    )
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    fig.colorbar(sc, ax=ax, shrink=0.7, label="residual (mm)")
    return _svg(fig, f"{salt}-3d")


def methods(rows: Sequence[MethodComparison], salt: str) -> str:
    """The paper's Fig. 9: each registration method's error at the validation poses."""
    ok = [r for r in rows if not r.error]
    fig = _figure(7.0, 2.8)
    ax = fig.add_subplot()
    x = np.arange(len(ok))
    ax.bar(
        x - 0.2, [r.fit_rms_mm for r in ok], 0.4, color=PAPER, label="fit RMS (calibration poses)"
    )
    ax.bar(x + 0.2, [r.validation_rms_mm for r in ok], 0.4, color=AFTER, label="validation RMS")
    ax.set_xticks(x, [r.method for r in ok])
    ax.set_ylabel("mm")
    ax.legend(frameon=False, fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    return _svg(fig, f"{salt}-methods")


VERDICT_COLOURS = {"ok": AFTER, "warning": "#d08c00", "recalibrate": BEFORE}


def control_chart(
    days: Array,
    rms: Array,
    warning: Array,
    limit: Array,
    verdicts: Sequence[str],
    trend: tuple[float, float] | None,
    salt: str,
    *,
    mark: int | None = None,
) -> str:
    """The checks of one model: each one's RMS error against its warning and
    recalibration limits, over the days since the model became valid; ``trend`` (slope
    mm/day, intercept mm) drawn over the checks' span; ``mark``: this report's check."""
    fig = _figure(7.0, 3.2)
    ax = fig.add_subplot()
    ax.step(days, limit, where="post", color=BEFORE, lw=1, label="recalibrate limit")
    ax.step(days, warning, where="post", color="#d08c00", lw=1, ls="--", label="warning limit")
    for verdict, colour in VERDICT_COLOURS.items():
        keep = np.array([v == verdict for v in verdicts], dtype=bool)
        if keep.any():
            ax.plot(days[keep], rms[keep], "o", ms=6, color=colour, label=f"check: {verdict}")
    if mark is not None:
        ax.plot(days[mark], rms[mark], "o", ms=12, mfc="none", mec="#222", label="this check")
    if trend is not None:
        x = np.array([days.min(), days.max()])
        ax.plot(x, trend[1] + trend[0] * x, color=PAPER, lw=1, ls=":", label="trend (ok checks)")
    ax.set_xlabel("days since the model became valid")
    ax.set_ylabel("RMS error (mm)")
    _log_y(ax)
    ax.set_title("checks of the model")
    ax.legend(frameon=False, fontsize=8, loc="upper left")
    ax.grid(alpha=0.3, which="both")
    return _svg(fig, salt)
