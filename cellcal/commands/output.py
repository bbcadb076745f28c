"""Helpers shared by the subcommands: JSON output and warnings."""

from __future__ import annotations

import json
from typing import Any

import click

from cellcal.plainvalues import plain


def jsonable(value: Any) -> Any:
    """Plain JSON values; NaN and inf become null (JSON has no such numbers)."""
    return plain(value, lambda _: None)


def print_json(obj: dict[str, Any]) -> None:
    """One JSON object on stdout, nothing else there."""
    click.echo(json.dumps(jsonable(obj), indent=2))


def warn(message: str) -> None:
    click.echo(f"cellcal: warning: {message}", err=True)


#: Seeds: what numpy's generators accept, and what SQLite stores.
SEED = click.IntRange(0, 2**32 - 1)


class FiniteFloat(click.ParamType[float, Any]):
    """A finite float not below ``minimum`` nor above ``maximum`` (NaN and inf are refused
    by name)."""

    name = "number"

    def __init__(
        self,
        minimum: float | None = 0.0,
        *,
        open_min: bool = False,
        maximum: float | None = None,
        why_max: str = "",
    ) -> None:
        self.minimum = minimum
        self.open_min = open_min
        self.maximum = maximum
        self.why_max = why_max

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        try:
            x = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if x != x or x in (float("inf"), float("-inf")):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        if self.minimum is not None and (x < self.minimum or (self.open_min and x == self.minimum)):
            bound = "above" if self.open_min else "at least"
            self.fail(f"{value!r} must be {bound} {self.minimum:g}", param, ctx)
        if self.maximum is not None and x > self.maximum:
            self.fail(f"{value!r} must be at most {self.maximum:g}{self.why_max}", param, ctx)
        return x


NON_NEGATIVE = FiniteFloat(0.0)
#: --time-scale: wall seconds per simulated second. Above 100 a 7 s dwell takes 12 min
#: and a move outlasts every timeout: slow motion for a demo, not an hours-long wait.
TIME_SCALE = FiniteFloat(
    0.0, maximum=100.0, why_max=" (wall seconds per simulated second: 1 is real time)"
)
POSITIVE = FiniteFloat(0.0, open_min=True)
