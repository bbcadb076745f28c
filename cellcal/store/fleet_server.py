"""The fleet's central PostgreSQL (psycopg 3): its schema, created and migrated by
cellcal, and the idempotent writes of what a cell sends.

The schema mirrors the campaign database's tables that hold campaigns, their analysis,
models and checks (``store/outbox.py``: :data:`FLEET_TABLES`), each with a ``cell`` column
first and the same columns after it (SQLite's INTEGER, REAL, TEXT as bigint, double
precision, text); a row's key is its cell and its id in that cell (``pose_stats``: cell,
pose and sensor), so that a row sent twice is written once. ``cells`` holds each cell's
line and when it last sent; ``cellcal_fleet`` the schema version. A server whose schema is
of another version is refused in one line, never written to.

A batch of rows goes in by ``COPY`` into a temporary table, then one ``INSERT … SELECT …
ON CONFLICT``: rows that can change (a campaign's status, a model's end) are updated,
the others left as they are. An entry of the outbox is one transaction."""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import psycopg
from psycopg import sql

from cellcal.errors import UserError
from cellcal.fleet_config import redacted
from cellcal.store.outbox import FLEET_TABLES, Rows, table_columns
from cellcal.store.schema import SCHEMA_VERSION, column_types

#: the version of the fleet's PostgreSQL schema this cellcal writes
FLEET_SCHEMA_VERSION = 1
#: rows that change after they are first sent: updated when sent again
MUTABLE = frozenset({"campaigns", "models"})
PG_TYPES = {"INTEGER": "bigint", "REAL": "double precision", "TEXT": "text"}
#: how long a connection may take (s)
CONNECT_TIMEOUT_S = 10


class FleetError(UserError):
    """The fleet's server cannot be used (unreachable, refused, another schema)."""


def key_columns(table: str) -> tuple[str, ...]:
    return ("cell", "pose_id", "sensor") if table == "pose_stats" else ("cell", "id")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    if "no password supplied" in line or "password authentication failed" in line:
        line += " (libpq takes the password from PGPASSFILE, ~/.pgpass or a service file)"
    return line


def _passfile_readable_by_others(url: str) -> None:
    """libpq ignores a password file that others may read, with a warning line of its
    own on stderr before the failure: said here instead, in one line."""
    path = Path(os.environ.get("PGPASSFILE") or Path.home() / ".pgpass")
    try:
        mode = path.stat().st_mode
    except OSError:
        return  # none: libpq says what is missing
    if stat.S_ISREG(mode) and mode & 0o077:
        raise FleetError(
            f"fleet server {redacted(url)}: the password file {path} may be read by others "
            f"(mode {stat.S_IMODE(mode):04o}), so libpq ignores it: chmod 600 {path}"
        )


@contextlib.contextmanager
def connected(url: str, application: str = "cellcal") -> Iterator[psycopg.Connection[Any]]:
    """A connection to the fleet's server; any failure to reach or use it is one line
    naming the server (its password, if libpq found one, never shown)."""
    _passfile_readable_by_others(url)
    try:
        conn = psycopg.connect(url, connect_timeout=CONNECT_TIMEOUT_S, application_name=application)
    except psycopg.Error as exc:
        raise FleetError(f"fleet server {redacted(url)}: {_first_line(exc)}") from None
    try:
        yield conn
    except psycopg.Error as exc:
        raise FleetError(f"fleet server {redacted(url)}: {_first_line(exc)}") from None
    finally:
        with contextlib.suppress(Exception):
            conn.close()


def _ddl() -> list[sql.Composed]:
    types = column_types(SCHEMA_VERSION)
    out = [
        sql.SQL(
            "CREATE TABLE cells (cell text PRIMARY KEY, line text, database_id text NOT NULL, "
            "first_seen timestamptz NOT NULL DEFAULT now(), "
            "last_seen timestamptz NOT NULL DEFAULT now())"
        ).format()
    ]
    for table in FLEET_TABLES:
        columns: list[sql.Composable] = [sql.SQL("cell text NOT NULL REFERENCES cells(cell)")]
        for name in table_columns(table):
            kind = PG_TYPES.get(types[table][name].upper(), "text")
            columns.append(sql.SQL("{} {}").format(sql.Identifier(name), sql.SQL(kind)))
        key = sql.SQL(", ").join(map(sql.Identifier, key_columns(table)))
        out.append(
            sql.SQL("CREATE TABLE {} ({}, PRIMARY KEY ({}))").format(
                sql.Identifier(table), sql.SQL(", ").join(columns), key
            )
        )
    for table, column in (
        ("poses", "campaign_id"),
        ("samples", "pose_id"),
        ("events", "campaign_id"),
    ):
        out.append(
            sql.SQL("CREATE INDEX ON {} (cell, {})").format(
                sql.Identifier(table), sql.Identifier(column)
            )
        )
    return out


def _tables(conn: psycopg.Connection[Any]) -> list[str]:
    """The tables in the connection's schema (``current_schema()``, where cellcal's go)."""
    return [
        r[0]
        for r in conn.execute(
            "SELECT table_name FROM information_schema.tables "
            "WHERE table_schema = current_schema() ORDER BY table_name"
        ).fetchall()
    ]


def _another_programs(url: str, tables: list[str]) -> FleetError:
    named = ", ".join(tables[:3]) + (f" and {len(tables) - 3} more" if len(tables) > 3 else "")
    return FleetError(
        f"fleet server {redacted(url)}: the database has tables of another program "
        f"({named}; no cellcal_fleet table); give cellcal a database of its own"
    )


def ensure_schema(conn: psycopg.Connection[Any], url: str) -> None:
    """Create the fleet's schema on an empty database, or check the one there is of
    this cellcal's version; anything else — a database with any table of another
    program — is refused in one line, before anything is written."""
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(20181122)")  # one creator at a time
        tables = _tables(conn)
        if "cellcal_fleet" not in tables:
            if tables:
                raise _another_programs(url, tables)
            conn.execute("CREATE TABLE cellcal_fleet (key text PRIMARY KEY, value text NOT NULL)")
            for statement in _ddl():
                conn.execute(statement)
            conn.execute(
                "INSERT INTO cellcal_fleet VALUES ('schema_version', %s)",
                (str(FLEET_SCHEMA_VERSION),),
            )
            return
        _same_version(conn, url)


def require_schema(conn: psycopg.Connection[Any], url: str) -> None:
    """For a reader (``cellcal fleet report``), which writes nothing: the fleet's schema
    of this cellcal's version must be there; a database without it is refused in one
    line (a mistyped name would otherwise give an empty report)."""
    tables = _tables(conn)
    if "cellcal_fleet" not in tables:
        if tables:
            raise _another_programs(url, tables)
        raise FleetError(
            f"fleet server {redacted(url)}: no fleet in this database (no cellcal_fleet "
            "table): check its name; the cells' `cellcal fleet sync` makes the fleet"
        )
    _same_version(conn, url)


def _same_version(conn: psycopg.Connection[Any], url: str) -> None:
    row = conn.execute("SELECT value FROM cellcal_fleet WHERE key = 'schema_version'").fetchone()
    version = row[0] if row else "none"
    if version != str(FLEET_SCHEMA_VERSION):
        raise FleetError(
            f"fleet server {redacted(url)}: its fleet schema is version {version}, this "
            f"cellcal writes version {FLEET_SCHEMA_VERSION}; upgrade the cellcal of "
            "every cell together with the server's schema"
        )


def merged(batches: Sequence[Rows]) -> list[Rows]:
    """Several entries' rows as one batch per table, in order; a row that comes twice
    (a model made and ended, a campaign refused then complete) once, as it came last."""
    out: dict[str, tuple[tuple[str, ...], dict[tuple[object, ...], tuple[object, ...]]]] = {}
    for b in batches:
        columns, rows = out.setdefault(b.table, (b.columns, {}))
        at = [columns.index(k) for k in key_columns(b.table)[1:]]
        for row in b.rows:
            key = tuple(row[i] for i in at)
            rows.pop(key, None)
            rows[key] = row
    return [Rows(t, columns, list(rows.values())) for t, (columns, rows) in out.items()]


def write_rows(conn: psycopg.Connection[Any], cell: str, batches: Sequence[Rows]) -> None:
    """Rows of one cell into their tables, idempotently (inside the caller's
    transaction): COPY into a temporary table, then INSERT … ON CONFLICT. Give each
    table once (:func:`merged`): a key twice in one statement is an error."""
    for b in batches:
        if not b.rows:
            continue
        columns = ("cell", *b.columns)
        stage = sql.Identifier(f"stage_{b.table}")
        conn.execute(  # once per connection: emptied at each commit
            sql.SQL("CREATE TEMP TABLE IF NOT EXISTS {} (LIKE {}) ON COMMIT DELETE ROWS").format(
                stage, sql.Identifier(b.table)
            )
        )
        names = sql.SQL(", ").join(map(sql.Identifier, columns))
        with conn.cursor().copy(sql.SQL("COPY {} ({}) FROM STDIN").format(stage, names)) as copy:
            for row in b.rows:
                copy.write_row((cell, *row))
        keys = key_columns(b.table)
        if b.table in MUTABLE:
            changes = sql.SQL(", ").join(
                sql.SQL("{0} = EXCLUDED.{0}").format(sql.Identifier(c))
                for c in columns
                if c not in keys
            )
            action: sql.Composable = sql.SQL("DO UPDATE SET {}").format(changes)
        else:
            action = sql.SQL("DO NOTHING")
        conn.execute(
            sql.SQL("INSERT INTO {t} ({n}) SELECT {n} FROM {s} ON CONFLICT ({k}) {a}").format(
                t=sql.Identifier(b.table),
                n=names,
                s=stage,
                k=sql.SQL(", ").join(map(sql.Identifier, keys)),
                a=action,
            )
        )


def note_cell(conn: psycopg.Connection[Any], cell: str, line: str | None, database_id: str) -> None:
    """The cell in ``cells`` (its line as configured now, the time it last sent). A cell
    of that name sent from another campaign database is refused: its ids would mix
    with this one's (two cells configured with one name, or a cell's new database)."""
    row = conn.execute(
        """INSERT INTO cells (cell, line, database_id) VALUES (%s, %s, %s) ON CONFLICT (cell)
        DO UPDATE SET line = EXCLUDED.line, last_seen = now()
        WHERE cells.database_id = EXCLUDED.database_id RETURNING cell""",
        (cell, line, database_id),
    ).fetchone()
    if row is None:
        raise FleetError(
            f"cell {cell} is in the fleet already, sent from another campaign database: "
            "give each cell its own name ([fleet] cell); a cell's new database needs a new "
            "name too"
        )


def count_rows(conn: psycopg.Connection[Any], table: str, cell: str | None = None) -> int:
    """How many rows a fleet table holds (of one cell)."""
    query = sql.SQL("SELECT count(*) FROM {}").format(sql.Identifier(table))
    if cell is not None:
        query = sql.SQL("{} WHERE cell = %s").format(query)
    row = conn.execute(query, (cell,) if cell is not None else ()).fetchone()
    return int(row[0]) if row else 0
