"""``cellcal fleet``: a cell's replication to the fleet's PostgreSQL (``status``,
``sync``) and the fleet's page across cells (``report``)."""

from __future__ import annotations

from typing import Any

import click

from cellcal.commands.output import print_json
from cellcal.commands.service import DEFAULT_CONFIG as SERVICE_CONFIG
from cellcal.config import CellConfig, load_config
from cellcal.errors import InputError
from cellcal.fleet_config import FleetConfig, redacted

CONFIG = click.option(
    "--config",
    "config_path",
    default=SERVICE_CONFIG,
    show_default=True,
    help="Cell configuration (TOML) with its [fleet] table.",
)
JSON = click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")


@click.group()
def fleet() -> None:
    """A cell's replication to the fleet's PostgreSQL, and the fleet's page."""


def _fleet_of(config_path: str) -> tuple[CellConfig, FleetConfig]:
    from pathlib import Path

    if config_path == SERVICE_CONFIG and not Path(config_path).is_file():
        raise InputError(f"{SERVICE_CONFIG}: no such file (the service's); give --config FILE")
    config = load_config(config_path)
    if config.fleet is None:
        raise InputError(f"{config_path}: no [fleet] table (database, cell): nothing to replicate")
    return config, config.fleet


def _database(config: CellConfig, db_path: str | None) -> str:
    from pathlib import Path

    from cellcal.store.connection import database_path

    db = database_path(db_path if db_path is not None else config.storage.database)
    if not Path(db).is_file():
        raise InputError(f"{db}: no such database")
    return db


@fleet.command("status")
@CONFIG
@click.option("--db", "db_path", help="The campaign database (default: the config's).")
@JSON
def status(config_path: str, db_path: str | None, as_json: bool) -> None:
    """The replication's state: the server, the last row sent per table, the entries
    waiting, the last error (read from the campaign database; the server is not asked)."""
    from cellcal.store.database import Store

    config, f = _fleet_of(config_path)
    db = _database(config, db_path)
    store = Store(db, readonly=True)
    try:
        p = store.fleet_progress()
    finally:
        store.close()
    doc: dict[str, Any] = {
        "server": redacted(f.database),
        "cell": f.cell,
        "line": f.line,
        "database": db,
        "waiting": p.waiting,
        "oldest_waiting": p.oldest_waiting,
        "sent": {t: {"last_id": last, "rows": n} for t, (last, n) in p.sent.items()},
        "last_sent": p.state.get("last_sent"),
        "last_attempt": p.state.get("last_attempt"),
        "last_error": p.state.get("last_error") or None,
        "last_error_at": p.state.get("last_error_at") if p.state.get("last_error") else None,
    }
    if as_json:
        print_json(doc)
        return
    click.echo(f"cell {f.cell} → {doc['server']} (database {db})")
    oldest = f", the oldest since {p.oldest_waiting}" if p.oldest_waiting else ""
    click.echo(f"  waiting: {p.waiting} entries{oldest}")
    last, attempt = doc["last_sent"] or "never", doc["last_attempt"] or "never"
    click.echo(f"  last sent: {last}; last attempt: {attempt}")
    for table, (last, n) in p.sent.items():
        click.echo(f"  {table:<14}{n:>9} rows sent" + (f", last id {last}" if last else ""))
    if doc["last_error"]:
        click.echo(f"  last error ({doc['last_error_at']}): {doc['last_error']}")


@fleet.command("sync")
@CONFIG
@click.option("--db", "db_path", help="The campaign database (default: the config's).")
@JSON
def sync_command(config_path: str, db_path: str | None, as_json: bool) -> None:
    """Send what waits to the fleet's server, then exit (for a cell without the service)."""
    from cellcal.fleet_sync import sync
    from cellcal.store.database import Store

    config, f = _fleet_of(config_path)
    db = _database(config, db_path)
    store = Store(db)
    try:
        result = sync(store, f)
    finally:
        store.close()
    if as_json:
        print_json(
            {
                "server": result.server,
                "cell": f.cell,
                "sent": result.sent,
                "rows": result.rows,
                "waiting": result.waiting,
            }
        )
        return
    entries = "entry" if result.sent == 1 else "entries"
    rows = "row" if result.rows == 1 else "rows"
    click.echo(
        f"cell {f.cell}: {result.sent} {entries} ({result.rows} {rows}) sent to "
        f"{result.server}; {result.waiting} waiting"
    )


@fleet.command("report")
@click.option("--database", "url", required=True, help="The fleet's PostgreSQL (a libpq URL).")
@click.option("--out", "out", required=True, help="Folder for index.html and fleet.json.")
@click.option("--line", "lines", multiple=True, help="Only the cells of this line (repeatable).")
@click.option("--cell", "cells", multiple=True, help="Only this cell (repeatable).")
@click.option(
    "--check-every",
    "every_days",
    type=click.FloatRange(min=0, min_open=True, max=3650),
    default=7.0,
    show_default=True,
    help="Days between checks: when a cell's next check is due.",
)
@JSON
def report(
    url: str,
    out: str,
    lines: tuple[str, ...],
    cells: tuple[str, ...],
    every_days: float,
    as_json: bool,
) -> None:
    """The fleet's page across cells: each robot's current model and its age, checks due
    and overdue, drift per robot, accuracy before and after per calibration; index.html
    (self-contained) and fleet.json in --out."""
    import json
    from datetime import timedelta
    from pathlib import Path

    from cellcal.extras import needs, require
    from cellcal.files.outputs import check_output_file, write_atomically
    from cellcal.fleet_config import url_problem

    problem = url_problem(url)
    if problem is not None:
        raise InputError(f"--database: {problem}")
    require("cellcal fleet report", "matplotlib")
    with needs("cellcal fleet report"):
        from cellcal.reports.fleet_page import cell_rows, fleet_html
        from cellcal.store.fleet_queries import read_fleet
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out {folder}: exists and is not a folder")
    every = timedelta(days=every_days)
    data = read_fleet(url, lines, cells)
    rows = cell_rows(data, every)
    doc = {
        "server": redacted(url),
        "generated": data.now.isoformat(),
        "check_every_days": every_days,
        "cells": [r.as_dict() for r in rows],
    }
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {folder}: cannot create ({exc.strerror})") from None
    files = {
        "index.html": fleet_html(rows, data, redacted(url), every),
        "fleet.json": json.dumps(doc, indent=2) + "\n",
    }
    for name in files:
        check_output_file(folder / name)
    for name, text in files.items():
        write_atomically(folder / name, text)
    if as_json:
        print_json(doc)
        return
    due = sum(r.due in ("due", "overdue", "no model") for r in rows)
    needs_ = "needs" if due == 1 else "need"
    noun = "cell" if len(rows) == 1 else "cells"
    click.echo(f"fleet of {len(rows)} {noun}: {due} {needs_} a check or a calibration now")
    click.echo(f"report: {folder / 'index.html'}")
