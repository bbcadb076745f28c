"""``cellcal tracker``: measure once with a tracker — one that speaks the line protocol
(``--dialect line-protocol``, the default: the version the tracker announces) or a Leica
tracker on emScon TPI (``--dialect emscon``) — or, with ``--conformance``, check that a
line-protocol tracker or bridge answers every request and fault a campaign relies on
(exit 1 when it does not: ``docs/tracker.md``)."""

from __future__ import annotations

from typing import Any

import click
import numpy as np

from cellcal.calib.geometry import Array
from cellcal.commands.output import POSITIVE, FiniteFloat, print_json
from cellcal.drivers.base import Series
from cellcal.errors import InputError


@click.command()
@click.option(
    "--address",
    help="Line protocol: a pyserial URL (/dev/ttyUSB0, a pty path, socket://HOST:PORT); "
    "emScon: HOST[:PORT] (port 700 by default).",
)
@click.option("--url", help="The same as --address (its earlier name).")
@click.option(
    "--dialect",
    type=click.Choice(["line-protocol", "emscon"]),
    default="line-protocol",
    show_default=True,
)
@click.option("--samples", type=click.IntRange(1, 10000), default=20, show_default=True)
@click.option(
    "--rate",
    "rate_hz",
    type=FiniteFloat(0.0, open_min=True),
    default=10.0,
    show_default=True,
    help="Line protocol: samples per second (emScon measures each for 500 ms).",
)
@click.option(
    "--timeout",
    type=POSITIVE,
    default=5.0,
    show_default=True,
    help="Seconds per request.",
)
@click.option(
    "--conformance",
    is_flag=True,
    help="Line protocol: run every request and fault a campaign relies on and say what the "
    "tracker got wrong (exit 1 when something does not hold).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def tracker(
    address: str | None,
    url: str | None,
    dialect: str,
    samples: int,
    rate_hz: float,
    timeout: float,
    conformance: bool,
    as_json: bool,
) -> None:
    """Connect to a tracker, identify it, initialise it and measure its target; or check
    its line protocol (--conformance)."""
    if (address is None) == (url is None):
        raise InputError("give the tracker's --address (or --url), once")
    where = address if address is not None else url
    assert where is not None
    if conformance:
        if dialect != "line-protocol":
            raise InputError("--conformance: for the line protocol (--dialect line-protocol)")
        _conformance(where, rate_hz, timeout, as_json)
        return
    if dialect == "emscon":
        out, text = _emscon(where, samples, timeout)
    else:
        out, text = _line_protocol(where, samples, rate_hz, timeout)
    if as_json:
        print_json(out)
        return
    for line in text:
        click.echo(line)


def _mean_cov(series: Series) -> Array:
    """The covariance of the mean (mm²): the samples' own covariances when the tracker
    reports them (averaged, over n), else their scatter's (over n)."""
    if series.cov is not None:
        out: Array = series.cov.mean(axis=0) / series.n
        return out
    if series.n < 2:
        return np.full((3, 3), np.nan)
    scatter: Array = np.cov(series.xyz, rowvar=False) / series.n
    return scatter


def _common(series: Series) -> tuple[dict[str, Any], list[str]]:
    mean, std = series.mean, series.std
    out: dict[str, Any] = {"n": series.n, "mean_mm": mean, "std_mm": std}
    out["cov_mm2"] = _mean_cov(series)
    line = (
        f"{series.n} samples: mean ({mean[0]:.4f}, {mean[1]:.4f}, {mean[2]:.4f}) mm, "
        f"σ ({std[0]:.4f}, {std[1]:.4f}, {std[2]:.4f}) mm, σ of the mean "
        f"{float(np.linalg.norm(std)) / np.sqrt(series.n):.4f} mm"
    )
    text = [line]
    if series.meteo is not None:
        t, p, rh = series.meteo.mean(axis=0)
        out |= {"temperature_c": t, "pressure_hpa": p, "humidity_pct": rh}
        text.append(f"air {t:.2f} °C, {p:.2f} hPa, {rh:.1f} % RH (as the tracker used it)")
    return out, text


def _line_protocol(
    url: str, samples: int, rate_hz: float, timeout: float
) -> tuple[dict[str, Any], list[str]]:
    from cellcal.drivers.tracker import LineTracker

    t = LineTracker("tracker", url, timeout=timeout, protocol=None)
    t.connect()
    try:
        series = t.measure(samples, rate_hz)
    finally:
        t.close()
    idn = t.identity
    idn_text = "" if idn is None else f"{idn.maker},{idn.model},{idn.serial},{idn.firmware}"
    events = [f"{e.name} {e.payload}".strip() for _, e in t.events]
    common, text = _common(series)
    out = {
        "idn": idn_text,
        **common,
        "retries": t.retries,
        "events": events,
        "garbage_lines": t.garbage,
        "reconnections": t.reconnections,
        "device_time_s": [float(series.device_time[0]), float(series.device_time[-1])],
    }
    out["protocol"] = t.version
    return out, [
        f"tracker {idn_text} at {url} (line protocol version {t.version})",
        *text,
        f"retries {t.retries}, reconnections {t.reconnections}, garbage lines {t.garbage}, "
        f"events: {', '.join(events) or 'none'}",
    ]


def _emscon(address: str, samples: int, timeout: float) -> tuple[dict[str, Any], list[str]]:
    from cellcal.drivers.emscon import EmsconOptions, EmsconTracker
    from cellcal.drivers.emscon_packets import event_text

    options = EmsconOptions(name="tracker", address=address, timeout_s=timeout)
    t = EmsconTracker(options)
    t.connect()
    try:
        series = t.measure(samples, 1.0)
    finally:
        t.close()
    d = t.describe()
    idn_text = f"{d.maker},{d.model or ''},{d.serial or ''},{d.firmware or ''}"
    common, text = _common(series)
    events = [event_text(packet) for _, packet in t.link.events.seen]
    out = {"idn": idn_text, **common, "retries": series.retries, "events": events}
    if series.note:
        out["note"] = series.note
    return out, [
        f"tracker {idn_text} at {address} (emScon)",
        *text,
        f"retries {series.retries}" + (f": {series.note}" if series.note else ""),
    ]


def _conformance(address: str, rate_hz: float, timeout: float, as_json: bool) -> None:
    from cellcal.drivers.tracker_conformance import check_conformance

    click.echo(f"cellcal tracker: checking the line protocol of {address}", err=True)
    result = check_conformance(address, timeout=timeout, rate_hz=rate_hz)
    if as_json:
        print_json(
            {
                "address": result.address,
                "idn": result.idn,
                "versions": list(result.versions),
                "passed": result.passed,
                "failed": list(result.failed),
                "checks": [
                    {"name": c.name, "ok": c.ok, "expected": c.expected, "got": c.got}
                    for c in result.checks
                ],
            }
        )
    else:
        versions = ", ".join(map(str, result.versions))
        click.echo(f"tracker {result.idn} at {address}: line protocol version {versions}")
        for c in result.checks:
            if c.ok:
                click.echo(f"ok    {c.name}: {c.got}")
            else:
                click.echo(f"FAIL  {c.name}: expected {c.expected}, got {c.got}")
        n = len(result.checks)
        if result.passed:
            click.echo(f"all {n} checks hold")
        else:
            click.echo(f"{len(result.failed)} of {n} checks failed: {', '.join(result.failed)}")
    if not result.passed:
        raise click.exceptions.Exit(1)
