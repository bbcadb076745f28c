"""Helpers shared by the subcommands: JSON output and warnings."""

from __future__ import annotations

import json
import math
from typing import Any

import click
import numpy as np


def jsonable(value: Any) -> Any:
    """Plain JSON values; NaN and inf become null (JSON has no such numbers)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else None
    return value


def print_json(obj: dict[str, Any]) -> None:
    """One JSON object on stdout, nothing else there."""
    click.echo(json.dumps(jsonable(obj), indent=2))


def warn(message: str) -> None:
    click.echo(f"cellcal: warning: {message}", err=True)
