"""The fleet's outbox in the campaign database (schema 7): what is waiting to go to the
central PostgreSQL, in order, and what went. A mixin of
:class:`~cellcal.store.database.Store`.

Triggers (``store/schema.py``) add an entry in the transaction that makes a change: a
campaign that finished (``campaign``: it is sent whole, its rows read when it is sent),
a model made or ended (``model``). The sender (``cellcal/fleet.py``) takes the entries
oldest first, writes each one in one transaction on the server, and only then marks it
sent here: a crash between the two sends it again, which the server's keys make
harmless (at least once, never twice)."""

from __future__ import annotations

import sqlite3
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from cellcal.store.schema import SCHEMA_VERSION, column_types, utc_now

#: the tables a finished campaign is sent with, and how each one's rows are found
CAMPAIGN_TABLES: dict[str, str] = {
    "campaigns": "id = ?",
    "poses": "campaign_id = ?",
    "samples": "pose_id IN (SELECT id FROM poses WHERE campaign_id = ?)",
    "pose_stats": "pose_id IN (SELECT id FROM poses WHERE campaign_id = ?)",
    "events": "campaign_id = ?",
    "registrations": "campaign_id = ?",
    "calibrations": "campaign_id = ?",
    "fused": "campaign_id = ?",
    "reports": "campaign_id = ?",
    "checks": "campaign_id = ?",
}
#: every table the fleet mirrors (a model is sent alone too)
FLEET_TABLES = (*CAMPAIGN_TABLES, "models")


class _Transaction(Protocol):
    def __enter__(self) -> sqlite3.Connection: ...

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None: ...


@dataclass(frozen=True)
class OutboxEntry:
    id: int
    kind: str
    ref: int
    created: str


@dataclass(frozen=True)
class Rows:
    """One table's rows of an entry: its columns (the schema's order) and the values."""

    table: str
    columns: tuple[str, ...]
    rows: list[tuple[object, ...]]


@dataclass(frozen=True)
class FleetProgress:
    """What the outbox says: entries waiting (and the oldest one's time), per table the
    last row id sent and how many rows, and the sender's last attempt, success and
    error (None: none)."""

    waiting: int
    oldest_waiting: str | None
    sent: dict[str, tuple[int | None, int]]
    state: dict[str, str]


def table_columns(table: str) -> tuple[str, ...]:
    """A table's columns in the schema's order (what the fleet's tables mirror)."""
    return tuple(column_types(SCHEMA_VERSION)[table])


class OutboxTables:
    conn: sqlite3.Connection
    path: str
    transaction: Callable[[], _Transaction]

    def _no_outbox(self) -> bool:
        return int(self.conn.execute("PRAGMA user_version").fetchone()[0]) < 7

    def waiting(self, limit: int = 1000) -> list[OutboxEntry]:
        """The entries not yet sent, oldest first."""
        if self._no_outbox():
            return []
        rows = self.conn.execute(
            "SELECT id, kind, ref, created FROM outbox WHERE sent IS NULL ORDER BY id LIMIT ?",
            (limit,),
        ).fetchall()
        return [OutboxEntry(*r) for r in rows]

    def entry_rows(self, entry: OutboxEntry) -> list[Rows]:
        """The rows an entry sends, as they are now: a campaign's in every table
        (:data:`CAMPAIGN_TABLES`), or one model's."""
        where = CAMPAIGN_TABLES if entry.kind == "campaign" else {"models": "id = ?"}
        out = []
        for table, condition in where.items():
            columns = table_columns(table)
            rows = self.conn.execute(
                f"SELECT {', '.join(columns)} FROM {table} WHERE {condition}", (entry.ref,)
            ).fetchall()
            out.append(Rows(table, columns, rows))
        return out

    def mark_sent(self, entries: Sequence[OutboxEntry], sent: Sequence[Rows]) -> None:
        """Entries the server committed: marked sent, with each table's last row id and
        count, in one transaction."""
        now = utc_now()
        with self.transaction():
            self.conn.executemany(
                "UPDATE outbox SET sent = ? WHERE id = ?", [(now, e.id) for e in entries]
            )
            for r in sent:
                if not r.rows:
                    continue
                last = max(int(str(row[0])) for row in r.rows) if r.columns[0] == "id" else None
                self.conn.execute(
                    """INSERT INTO fleet_sent (table_name, last_id, rows) VALUES (?, ?, ?)
                    ON CONFLICT (table_name) DO UPDATE SET
                    last_id = max(coalesce(last_id, 0), coalesce(excluded.last_id, 0)),
                    rows = rows + excluded.rows""",
                    (r.table, last, len(r.rows)),
                )
            self._set_state({"last_sent": now, "last_error": ""})

    def fleet_identity(self) -> str:
        """This database's identity in the fleet (made at its first sending, kept in
        ``fleet_state``): a cell's name is refused if another database sent it first."""
        row = self.conn.execute(
            "SELECT value FROM fleet_state WHERE key = 'database_id'"
        ).fetchone()
        if row is not None:
            return str(row[0])
        identity = uuid.uuid4().hex
        self.note_fleet({"database_id": identity})
        return identity

    def note_fleet(self, values: dict[str, str]) -> None:
        """The sender's state (its server, last attempt, last error), kept for the status."""
        with self.transaction():
            self._set_state(values)

    def _set_state(self, values: dict[str, str]) -> None:
        self.conn.executemany(
            """INSERT INTO fleet_state (key, value) VALUES (?, ?)
            ON CONFLICT (key) DO UPDATE SET value = excluded.value""",
            list(values.items()),
        )

    def fleet_progress(self) -> FleetProgress:
        if self._no_outbox():
            return FleetProgress(0, None, {}, {})
        waiting, oldest = self.conn.execute(
            "SELECT count(*), min(created) FROM outbox WHERE sent IS NULL"
        ).fetchone()
        sent = {
            str(t): (last, int(n))
            for t, last, n in self.conn.execute(
                "SELECT table_name, last_id, rows FROM fleet_sent ORDER BY table_name"
            )
        }
        state = {str(k): str(v) for k, v in self.conn.execute("SELECT key, value FROM fleet_state")}
        return FleetProgress(int(waiting), oldest, sent, state)
