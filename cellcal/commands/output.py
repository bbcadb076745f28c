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
