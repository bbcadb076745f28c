"""Fleet benchmark: many simulated cells, a year of each — weekly checks and quarterly
calibrations, every sample — replicated into one PostgreSQL started here (Debian's
package, a cluster in a temporary folder), each figure against a peer in the same run.

1. Replication throughput: ``cellcal.fleet_sync.sync`` of every cell (the outbox's
   entries, one transaction each, COPY into a temporary table then ``INSERT … ON
   CONFLICT``) against a plain ``COPY`` of the same rows, read from the same SQLite
   files, into tables of the same columns and types without keys, one transaction per
   cell, in another database of the same server. Goal: at least 0.5× the plain COPY's
   rows per second.
2. The fleet's page: ``cellcal fleet report``'s reading and writing (``read_fleet``,
   ``cell_rows``, ``fleet_html``, ``fleet.json``) against ``psql`` fetching the rows it
   shows (the same three queries' results, printed to nowhere). Goal: under 5 s.

A cell's year is made from real campaigns: one calibration and one check of the tracker
cell (``config/mock-cell-tracker.toml``, 130 and 12 poses of 20 samples) run by cellcal,
then copied within its database to 4 calibrations and 52 checks spread over a year, each
model ended by the next; the cells are copies of that database under their own names.

Usage: ``python benchmarks/fleet.py [--cells 200]`` (``--cells 20`` for a quick look).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cellcal.fleet_config import FleetConfig  # noqa: E402
from cellcal.fleet_sync import sync  # noqa: E402
from cellcal.store.database import Store  # noqa: E402
from cellcal.store.fleet_server import PG_TYPES  # noqa: E402
from cellcal.store.outbox import CAMPAIGN_TABLES, FLEET_TABLES, table_columns  # noqa: E402
from cellcal.store.schema import SCHEMA_VERSION, column_types  # noqa: E402
from tests.fleet.pg_server import PgServer  # noqa: E402

CELL = ROOT / "config" / "mock-cell-tracker.toml"
CHECKS, CALIBRATIONS = 52, 4
#: id offsets of the copies (a campaign has fewer poses, samples, rows than these)
STEP = {"campaigns": 1, "poses": 1_000, "samples": 100_000, "other": 10_000}


def _run(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "cellcal", *args], check=True, capture_output=True)


def template(folder: Path) -> Path:
    """One cell's year: a real calibration and check, then copies of them."""
    db = folder / "template.db"
    _run("run", "--mock", "--config", str(CELL), "--db", str(db))
    _run("check", "--mock", "--config", str(CELL), "--db", str(db))
    conn = sqlite3.connect(db)
    start = datetime(2026, 1, 5, 8, tzinfo=UTC)
    plan = [("calibration", 1, start + timedelta(weeks=13 * q)) for q in range(CALIBRATIONS)]
    plan += [("check", 2, start + timedelta(weeks=w, days=1)) for w in range(CHECKS)]
    plan.sort(key=lambda p: p[2])
    conn.execute("DELETE FROM outbox")
    models: list[int] = []
    new_cid = 2
    for _, src, when in plan:
        new_cid += 1
        model = _clone(conn, src, new_cid, when, models[-1] if models else None)
        if model is not None:
            models.append(model)
    for table in (*CAMPAIGN_TABLES, "models"):  # the originals go; their copies stay
        column = "id" if table == "campaigns" else "campaign_id"
        if table in ("samples", "pose_stats"):
            old = "SELECT id FROM poses WHERE campaign_id <= 2"
            conn.execute(f"DELETE FROM {table} WHERE pose_id IN ({old})")
        elif table != "poses":
            conn.execute(f"DELETE FROM {table} WHERE {column} <= 2")
    conn.execute("DELETE FROM poses WHERE campaign_id <= 2")
    conn.execute(
        """INSERT INTO outbox (kind, ref, created) SELECT kind, ref, created FROM (
            SELECT 'campaign' AS kind, id AS ref, finished AS created FROM campaigns
            UNION ALL SELECT 'model', id, created FROM models) ORDER BY created, kind, ref"""
    )
    conn.commit()
    conn.execute("VACUUM")
    conn.close()
    return db


def _clone(
    conn: sqlite3.Connection, src: int, cid: int, when: datetime, model: int | None
) -> int | None:
    """Campaign ``src`` copied as ``cid`` at ``when``; a calibration's model too (the
    previous one ended then): the new model's id."""
    k = cid - src
    stamp = when.isoformat(timespec="milliseconds")
    for table, condition in CAMPAIGN_TABLES.items():
        columns = table_columns(table)
        rows = conn.execute(
            f"SELECT {', '.join(columns)} FROM {table} WHERE {condition}", (src,)
        ).fetchall()
        out = []
        for row in rows:
            r = dict(zip(columns, row, strict=True))
            if "id" in r:
                r["id"] += k * STEP.get(table, STEP["other"])
            if "campaign_id" in r:
                r["campaign_id"] = cid
            if "pose_id" in r:
                r["pose_id"] += k * STEP["poses"]
            for stamp_column in ("created", "finished", "stored", "time"):
                if r.get(stamp_column):
                    r[stamp_column] = stamp
            if table == "checks":
                r["model_id"] = model
            out.append(tuple(r.values()))
        marks = ", ".join("?" * len(columns))
        conn.executemany(f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({marks})", out)
    if src != 1:
        return None
    text = conn.execute(
        "SELECT model_toml FROM calibrations WHERE campaign_id = ?", (cid,)
    ).fetchone()
    if model is not None:
        conn.execute(
            "UPDATE models SET valid_until = ?, ended_by = ? WHERE id = ?",
            (stamp, f"model of campaign {cid}", model),
        )
    new = conn.execute(
        "INSERT INTO models (campaign_id, created, valid_from, model_toml, digest) "
        "VALUES (?, ?, ?, ?, ?)",
        (cid, stamp, stamp, text[0], f"{cid:016x}"),
    ).lastrowid
    return int(new or 0)


def make_cells(folder: Path, db: Path, n: int) -> list[Path]:
    cells = []
    for i in range(n):
        path = folder / f"cell{i:03d}.db"
        shutil.copyfile(db, path)
        cells.append(path)
    return cells


def replicate(cells: list[Path], url: str) -> tuple[float, int]:
    rows = 0
    t0 = time.perf_counter()
    for i, db in enumerate(cells):
        store = Store(db)
        try:
            result = sync(
                store, FleetConfig(database=url, cell=f"cell{i:03d}", line=f"line{i // 20}")
            )
        finally:
            store.close()
        rows += result.rows
    return time.perf_counter() - t0, rows


def plain_copy(cells: list[Path], url: str) -> tuple[float, int]:
    """The peer: the same rows from the same files, COPY into tables without keys."""
    import psycopg

    types = column_types(SCHEMA_VERSION)
    with psycopg.connect(url, autocommit=True) as conn:  # the fleet's columns, no keys
        for table in FLEET_TABLES:
            names = ", ".join(
                f"{c} {PG_TYPES.get(types[table][c].upper(), 'text')}" for c in table_columns(table)
            )
            conn.execute(f"CREATE TABLE {table} (cell text, {names})")
    rows = 0
    t0 = time.perf_counter()
    with psycopg.connect(url) as conn:
        for i, db in enumerate(cells):
            store = Store(db, readonly=True)
            try:
                with conn.transaction():
                    for entry in store.waiting(1_000_000):
                        for b in store.entry_rows(entry):
                            if not b.rows:
                                continue
                            cols = ", ".join(("cell", *b.columns))
                            with conn.cursor().copy(f"COPY {b.table} ({cols}) FROM STDIN") as cp:
                                for row in b.rows:
                                    cp.write_row((f"cell{i:03d}", *row))
                            rows += len(b.rows)
            finally:
                store.close()
    return time.perf_counter() - t0, rows


def report(url: str, out: Path) -> float:
    from cellcal.commands.fleet import report as report_command

    t0 = time.perf_counter()
    report_command.main(["--database", url, "--out", str(out)], standalone_mode=False)
    return time.perf_counter() - t0


def psql_peer(pg: PgServer, database: str) -> float:
    queries = (
        "SELECT cell, line, last_seen FROM cells;"
        "SELECT cell, id, campaign_id, valid_from, digest FROM models WHERE valid_until IS NULL;"
        "SELECT cell, campaign_id, model_id, created, rms_mm, max_mm, warning_mm, limit_mm, "
        "verdict, cause FROM checks;"
        "SELECT c.cell, c.id, c.finished, (r.summary::jsonb -> 'validation_before' ->> 'rms_mm'),"
        " (r.summary::jsonb -> 'validation_after' ->> 'rms_mm') FROM campaigns c JOIN reports r"
        " ON r.cell = c.cell AND r.campaign_id = c.id WHERE c.kind = 'calibration';"
    )
    t0 = time.perf_counter()
    pg.psql(queries, database)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=200)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="cellcal-fleet-bench-"))
    pg = PgServer()
    try:
        pg.start()
        os.environ["PGPASSFILE"] = str(pg.passfile(folder))
        for name in ("fleet", "peer"):
            pg.create_database(name)
        t0 = time.perf_counter()
        cells = make_cells(folder, template(folder), args.cells)
        made = time.perf_counter() - t0
        print(f"{args.cells} cells of {CALIBRATIONS} calibrations and {CHECKS} checks each, "
              f"made in {made:.0f} s")  # fmt: skip
        t_copy, n_copy = plain_copy(cells, pg.url("peer"))
        t_sync, n_sync = replicate(cells, pg.url("fleet"))
        assert n_copy == n_sync, (n_copy, n_sync)
        copy_rate, sync_rate = n_copy / t_copy, n_sync / t_sync
        print(f"replication: {n_sync:,} rows in {t_sync:.1f} s, {sync_rate:,.0f} rows/s")
        print(f"  peer, plain COPY of the same rows: {t_copy:.1f} s, {copy_rate:,.0f} rows/s")
        ratio = sync_rate / copy_rate
        verdict = "met" if ratio >= 0.5 else "NOT met"
        print(f"  ratio {ratio:.2f}× the plain COPY (goal ≥ 0.5×): {verdict}")
        t_page = report(pg.url("fleet"), folder / "page")
        t_psql = psql_peer(pg, "fleet")
        print(f"fleet report of {args.cells} cells: {t_page:.2f} s (goal < 5 s: "
              f"{'met' if t_page < 5 else 'NOT met'})")  # fmt: skip
        print(f"  peer, psql fetching the rows it shows: {t_psql:.2f} s; "
              f"ratio {t_page / t_psql:.1f}×")  # fmt: skip
    finally:
        pg.remove()
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
