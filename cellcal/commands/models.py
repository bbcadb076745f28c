"""``cellcal models``: the built-in robot models."""

from __future__ import annotations

import math
from typing import Any

import click

from cellcal.commands.output import print_json
from cellcal.files.models import builtin_names, load_model


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def models(as_json: bool) -> None:
    """List the built-in robot models (use the name with --model)."""
    rows: list[dict[str, Any]] = []
    for name in builtin_names():
        m = load_model(name).model
        beta_rows = [i + 1 for i, p in enumerate(m.parallel) if p]
        rows.append(
            {
                "name": name,
                "convention": m.convention,
                "joints": m.dof,
                "beta_rows": beta_rows,
                "limits_deg": [
                    [round(math.degrees(j.q_min), 9), round(math.degrees(j.q_max), 9)]
                    for j in m.joints
                ],
            }
        )
    if as_json:
        print_json({"models": rows})
        return
    click.echo(f"{'name':<16}{'convention':<12}{'joints':<8}{'β rows (parallel axes)':<24}")
    for r in rows:
        beta = ", ".join(str(i) for i in r["beta_rows"]) or "—"
        click.echo(f"{r['name']:<16}{r['convention']:<12}{r['joints']:<8}{beta:<24}")
