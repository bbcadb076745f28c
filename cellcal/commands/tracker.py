"""``cellcal tracker``: measure once with any tracker that speaks the line protocol."""

from __future__ import annotations

import click
import numpy as np

from cellcal.commands.output import POSITIVE, FiniteFloat, print_json
from cellcal.drivers.tracker import LineTracker


@click.command()
@click.option(
    "--url", required=True, help="pyserial URL: /dev/ttyUSB0, a pty path, socket://HOST:PORT."
)
@click.option("--samples", type=click.IntRange(1, 10000), default=20, show_default=True)
@click.option(
    "--rate",
    "rate_hz",
    type=FiniteFloat(0.0, open_min=True),
    default=10.0,
    show_default=True,
)
@click.option(
    "--timeout",
    type=POSITIVE,
    default=5.0,
    show_default=True,
    help="Seconds per request.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def tracker(url: str, samples: int, rate_hz: float, timeout: float, as_json: bool) -> None:
    """Connect to a tracker, identify it, initialise it and measure its target."""
    t = LineTracker("tracker", url, timeout=timeout)
    t.connect()
    try:
        series = t.measure(samples, rate_hz)
    finally:
        t.close()
    idn = t.identity
    idn_text = "" if idn is None else f"{idn.maker},{idn.model},{idn.serial},{idn.firmware}"
    mean, std = series.mean, series.std
    events = [f"{e.name} {e.payload}".strip() for _, e in t.events]
    if as_json:
        print_json(
            {
                "idn": idn_text,
                "n": series.n,
                "mean_mm": mean,
                "std_mm": std,
                "retries": t.retries,
                "events": events,
                "garbage_lines": t.garbage,
                "reconnections": t.reconnections,
                "device_time_s": [float(series.device_time[0]), float(series.device_time[-1])],
            }
        )
        return
    click.echo(f"tracker {idn_text} at {url}")
    click.echo(
        f"{series.n} samples: mean ({mean[0]:.4f}, {mean[1]:.4f}, {mean[2]:.4f}) mm, "
        f"σ ({std[0]:.4f}, {std[1]:.4f}, {std[2]:.4f}) mm, σ of the mean "
        f"{float(np.linalg.norm(std)) / np.sqrt(series.n):.4f} mm"
    )
    click.echo(
        f"retries {t.retries}, reconnections {t.reconnections}, garbage lines {t.garbage}, "
        f"events: {', '.join(events) or 'none'}"
    )
