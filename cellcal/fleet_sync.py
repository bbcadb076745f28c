"""Replication of a cell's campaign database to the fleet's PostgreSQL: the outbox's
entries (``store/outbox.py``) sent oldest first, consecutive ones together in one
transaction on the server (``store/fleet_server.py``, up to :data:`BATCH_ROWS` rows),
marked sent here once committed. At least once, in order,
idempotent on the server: a lost network, a restarted server or a killed sender leave
the rest waiting, and the next sync goes on from there.

The acquisition never waits for it: the outbox is filled by triggers in the
transactions the campaign makes anyway, and the sending reads the database with a
connection of its own (``cellcal fleet sync``, or the service's sender thread,
:class:`Sender`)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from cellcal.errors import UserError
from cellcal.extras import needs
from cellcal.fleet_config import FleetConfig, redacted
from cellcal.store.database import Store
from cellcal.store.outbox import OutboxEntry, Rows
from cellcal.store.schema import utc_now

#: the service's sender: seconds between tries when there is nothing or it failed
IDLE_S, RETRY_MIN_S, RETRY_MAX_S = 5.0, 2.0, 300.0
#: entries go to the server in transactions of up to this many rows (or entries)
BATCH_ROWS, BATCH_ENTRIES = 50_000, 200


@dataclass(frozen=True)
class SyncResult:
    """A sync's work: entries and rows sent, entries still waiting."""

    server: str
    sent: int
    rows: int
    waiting: int


def sync(
    store: Store,
    fleet: FleetConfig,
    *,
    stop: threading.Event | None = None,
    limit: int | None = None,
) -> SyncResult:
    """Send what waits in ``store``'s outbox to ``fleet``'s server (at most ``limit``
    entries; until ``stop`` is set); with nothing waiting it still connects and checks
    the server's schema, so that bad settings show. A failure is recorded in the
    database (the status shows it) and raised as one line."""
    with needs("cellcal fleet"):
        from cellcal.store.fleet_server import (
            connected,
            ensure_schema,
            merged,
            note_cell,
            write_rows,
        )
    server = redacted(fleet.database)
    entries = store.waiting(limit or 1_000_000)
    sent = rows = 0
    store.note_fleet({"server": server, "last_attempt": utc_now()})
    identity = store.fleet_identity()
    try:
        with connected(fleet.database, f"cellcal {fleet.cell}") as conn:
            ensure_schema(conn, fleet.database)
            at = 0
            while at < len(entries) and not (stop is not None and stop.is_set()):
                group: list[OutboxEntry] = []  # consecutive entries, one transaction
                batches: list[Rows] = []
                n = 0
                while at < len(entries) and n < BATCH_ROWS and len(group) < BATCH_ENTRIES:
                    entry = entries[at]
                    read = store.entry_rows(entry)
                    group.append(entry)
                    batches += read
                    n += sum(len(b.rows) for b in read)
                    at += 1
                with conn.transaction():
                    note_cell(conn, fleet.cell, fleet.line, identity)
                    write_rows(conn, fleet.cell, merged(batches))
                store.mark_sent(group, batches)
                sent += len(group)
                rows += n
    except UserError as exc:
        store.note_fleet({"last_error": str(exc), "last_error_at": utc_now()})
        raise
    return SyncResult(server, sent, rows, len(store.waiting(1_000_000)))


class Sender:
    """The service's replication: a thread with its own connection to the campaign
    database (opened once: opening a database checks every page of it), which syncs
    whenever there is something waiting, and after a failure tries again later (2 s,
    doubling up to 5 min); ``stop()`` ends it."""

    def __init__(
        self, db_path: str, fleet: FleetConfig, log: Callable[[str], None] = print
    ) -> None:
        self.db_path = db_path
        self.fleet = fleet
        self.log = log
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="fleet-sender", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._thread.join(timeout)

    def _loop(self) -> None:
        wait, failing = IDLE_S, False
        store: Store | None = None  # kept open: opening checks the whole file
        while not self._stop.is_set():
            try:
                if store is None:
                    store = Store(self.db_path)
                # the server is asked only when something waits
                result = (
                    sync(store, self.fleet, stop=self._stop)
                    if store.waiting(1)
                    else SyncResult(redacted(self.fleet.database), 0, 0, 0)
                )
                if failing or result.sent:
                    self.log(
                        f"fleet: {result.sent} sent to {result.server}, {result.waiting} waiting"
                    )
                wait, failing = IDLE_S, False
            except UserError as exc:
                if not failing:
                    self.log(f"fleet: {exc}; trying again")
                wait = RETRY_MIN_S if not failing else min(wait * 2, RETRY_MAX_S)
                failing = True
            self._stop.wait(wait)
        if store is not None:
            store.close()
