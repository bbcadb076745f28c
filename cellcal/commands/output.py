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
    """A finite float not below ``minimum`` (NaN and inf are refused by name)."""

    name = "number"

    def __init__(self, minimum: float | None = 0.0, *, open_min: bool = False) -> None:
        self.minimum = minimum
        self.open_min = open_min

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
        return x


NON_NEGATIVE = FiniteFloat(0.0)
POSITIVE = FiniteFloat(0.0, open_min=True)
