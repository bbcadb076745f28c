"""``cellcal models``: the built-in robot models; with ``--cell``, the calibrated models a
cell has carried (from its campaign database), each with its validity and its checks."""

from __future__ import annotations

import math
from typing import Any

import click

from cellcal.commands.output import print_json
from cellcal.errors import InputError
from cellcal.files.models import builtin_names, load_model


@click.command()
@click.option(
    "--cell", is_flag=True, help="The cell's calibrated models, their validity and checks."
)
@click.option("--config", "config_path", help="--cell: the cell's configuration (its database).")
@click.option("--db", "db_path", help="--cell: the campaign database (default: the config's).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def models(cell: bool, config_path: str | None, db_path: str | None, as_json: bool) -> None:
    """List the built-in robot models (use the name with --model); with --cell, the
    models the cell has carried: since when, until when and why, and the checks since."""
    if cell:
        _cell_models(config_path, db_path, as_json)
        return
    if config_path is not None or db_path is not None:
        raise InputError("--config and --db go with --cell")
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
    click.echo(f"{'name':<16}{'convention':<12}{'joints':<8}β rows (parallel axes)")
    for r in rows:
        beta = ", ".join(str(i) for i in r["beta_rows"]) or "—"
        click.echo(f"{r['name']:<16}{r['convention']:<12}{r['joints']:<8}{beta}")


def _cell_models(config_path: str | None, db_path: str | None, as_json: bool) -> None:
    from pathlib import Path

    from cellcal.config import default_database, load_config
    from cellcal.store.connection import database_path
    from cellcal.store.database import Store

    if db_path is None:
        db_path = load_config(config_path).storage.database if config_path else default_database()
    database_path(db_path)
    if not Path(db_path).is_file():
        raise InputError(f"{db_path}: no such database")
    store = Store(db_path, readonly=True)
    try:
        found, checks = store.models(), store.checks()
    finally:
        store.close()
    rows: list[dict[str, Any]] = []
    for m in found:
        own = [c for c in checks if c.model_id == m.id]
        rows.append(
            {
                "id": m.id,
                "campaign_id": m.campaign_id,
                "digest": m.digest,
                "valid_from": m.valid_from,
                "valid_until": m.valid_until,
                "ended_by": m.ended_by,
                "current": m.current,
                "checks": [
                    {
                        "campaign_id": c.campaign_id,
                        "created": c.created,
                        "verdict": c.verdict,
                        "rms_mm": c.rms_mm,
                        "limit_mm": c.limit_mm,
                        "cause": c.cause,
                    }
                    for c in own
                ],
            }
        )
    if as_json:
        print_json({"database": db_path, "models": rows})
        return
    if not rows:
        click.echo(f"{db_path}: no calibrated model yet (cellcal run calibrates one)")
        return
    click.echo(f"{'model':<7}{'campaign':<10}{'valid from (UTC)':<21}{'until':<21}checks")
    for r in rows:
        until = "current" if r["current"] else _time(r["valid_until"])
        verdicts = [c["verdict"] for c in r["checks"]]
        shown = f"{len(verdicts)}" + (f", last {verdicts[-1]}" if verdicts else "")
        since = _time(r["valid_from"])
        click.echo(f"{r['id']:<7}{r['campaign_id']:<10}{since:<21}{until:<21}{shown}")
        if r["ended_by"]:
            click.echo(f"{'':<7}ended by {r['ended_by']}")


def _time(stamp: str) -> str:
    """A stored UTC time stamp to the second, as a table shows it."""
    return stamp[:19].replace("T", " ")
