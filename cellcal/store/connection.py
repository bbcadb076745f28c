"""The campaign database's SQLite connections: which paths may be a database, how a file
is opened (to write, or to read only), and what a failing SQLite call says.

* :func:`database_path` refuses, in one place, what is no database file: an empty path
  (which SQLite takes for a temporary database), ``:memory:`` (a campaign into memory is
  lost at exit), ``file:`` URIs and SQLite's other special names (``:…``), and a path
  that exists and is not a regular file (a folder, a FIFO, a device).
* Every statement, fetch and iteration of a connection opened here turns SQLite's errors
  into one :class:`StoreError` line that names the file and what is wrong with it —
  damaged, not SQLite, locked, read-only, a disk that is full, a table that lacks a
  column — wherever the code that meets it runs (the store, the report, the service);
  ``IntegrityError`` (a pose stored twice) and ``ProgrammingError`` (a bug) pass as they
  are.
* :class:`Transaction`: ``BEGIN IMMEDIATE`` … ``COMMIT``, or ``ROLLBACK`` on any
  exception; a write that fails says so and that what was committed is kept.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

from cellcal.errors import UserError

#: How long a writer waits for another connection's lock, s (the service and a reader).
WRITE_WAIT_S = 10.0
#: How long a reader waits, s.
READ_WAIT_S = 5.0


class StoreError(UserError):
    """A database that cannot be opened or used (not SQLite, newer schema, locked,
    damaged, read-only)."""


class SqliteError(StoreError):
    """SQLite's error on a database, as one line naming the file; ``cause``, the error."""

    def __init__(self, path: str, cause: sqlite3.Error) -> None:
        super().__init__(f"{path}: {describe(path, cause)}")
        self.path = path
        self.cause = cause


def database_path(path: str | os.PathLike[str]) -> str:
    """``path`` as given, if it can name a campaign database file; else one line saying
    why not (the one check of every ``--db`` and ``storage.database``)."""
    text = os.fspath(path)
    if not text.strip():
        raise StoreError(
            f"the database path {text!r} is empty (SQLite would take a temporary database, "
            "lost at exit): give the campaign database's file"
        )
    if text[:5].lower() == "file:":
        raise StoreError(
            f"{text}: an SQLite URI, not a file: give the campaign database's file path"
        )
    if text == ":memory:" or Path(text).name == ":memory:":
        raise StoreError(
            f"{text}: SQLite's name for a database in memory, lost when cellcal exits: give a file"
        )
    if text.startswith(":"):
        raise StoreError(
            f"{text}: names that begin with ':' are reserved by SQLite; a file of that name "
            f"is ./{text}"
        )
    try:
        mode = os.stat(text).st_mode
    except FileNotFoundError:
        return text  # a new database
    except OSError as exc:
        raise StoreError(f"{text}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise StoreError(f"{text}: exists and is not a regular file, as a database is")
    return text


def loads(path: str, text: str | None, what: str) -> Any:
    """A JSON value stored in the database; a damaged one is one line naming it."""
    try:
        return json.loads(text if text is not None else "null")
    except (TypeError, ValueError) as exc:
        raise StoreError(f"{path}: a damaged value in {what} ({exc})") from None


def damaged(path: str, detail: str) -> str:
    """What to say of a damaged file (``detail``: what SQLite found)."""
    return (
        f"the database file is damaged ({detail}); restore it from a backup, or save what "
        f"is readable with: sqlite3 {path} .recover"
    )


def describe(path: str, exc: sqlite3.Error) -> str:
    """What SQLite's error says about the file, with what to do where there is something."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    low = text.lower()
    if "malformed" in low or "corrupt" in low:
        return damaged(path, text)
    if "not a database" in low or "encrypted" in low:
        return f"not a cellcal database: not an SQLite database file ({text})"
    if "locked" in low or "busy" in low:
        return f"another program holds the database locked ({text}); try again when it is done"
    if "readonly" in low or "read-only" in low:
        return f"the database file or its folder is read-only ({text})"
    if "full" in low:
        return f"the disk is full ({text})"
    if "disk i/o" in low:
        return f"the database file cannot be read or written ({text}): a failing disk?"
    if "no such table" in low or "no such column" in low or "has no column" in low:
        return f"not a complete cellcal database ({text}): changed by another program?"
    if "unable to open" in low:
        return f"cannot open the database file ({text})"
    return text


def write_fault(fault: SqliteError) -> StoreError:
    """A failed write as one line with its likely cause; what was committed is kept."""
    return StoreError(
        f"{fault.path}: cannot write to the database: {describe(fault.path, fault.cause)}; "
        "every pose committed before is kept"
    )


@contextlib.contextmanager
def _sqlite_faults(path: str) -> Iterator[None]:
    try:
        yield
    except (sqlite3.IntegrityError, sqlite3.ProgrammingError):
        raise
    except sqlite3.DatabaseError as exc:
        raise SqliteError(path, exc) from None


class Cursor(sqlite3.Cursor):
    """A cursor whose SQLite errors are :class:`SqliteError` lines naming the file."""

    path = ""

    def execute(self, sql: str, parameters: Any = (), /) -> Cursor:
        with _sqlite_faults(self.path):
            super().execute(sql, parameters)
        return self

    def executemany(self, sql: str, seq_of_parameters: Any, /) -> Cursor:
        with _sqlite_faults(self.path):
            super().executemany(sql, seq_of_parameters)
        return self

    def executescript(self, sql_script: str, /) -> Cursor:
        with _sqlite_faults(self.path):
            super().executescript(sql_script)
        return self

    def fetchone(self) -> Any:
        with _sqlite_faults(self.path):
            return super().fetchone()

    def fetchmany(self, size: int | None = None) -> list[Any]:
        with _sqlite_faults(self.path):
            return super().fetchmany(self.arraysize if size is None else size)

    def fetchall(self) -> list[Any]:
        with _sqlite_faults(self.path):
            return super().fetchall()

    def __next__(self) -> Any:
        with _sqlite_faults(self.path):
            return super().__next__()


class Connection(sqlite3.Connection):
    """A connection to the database at ``path`` whose statements run on :class:`Cursor`."""

    path = ""

    def cursor(self, factory: Any = Cursor) -> Any:
        cur = super().cursor(factory)
        if isinstance(cur, Cursor):
            cur.path = self.path
        return cur

    def execute(self, sql: str, parameters: Any = (), /) -> Cursor:
        cur: Cursor = self.cursor()
        return cur.execute(sql, parameters)

    def executemany(self, sql: str, parameters: Any, /) -> Cursor:
        cur: Cursor = self.cursor()
        return cur.executemany(sql, parameters)

    def executescript(self, sql_script: str, /) -> Cursor:
        cur: Cursor = self.cursor()
        return cur.executescript(sql_script)


def _connect(target: str, path: str, *, timeout: float, uri: bool = False) -> Connection:
    with _sqlite_faults(path):
        conn = sqlite3.connect(
            target, isolation_level=None, timeout=timeout, uri=uri, factory=Connection
        )
    assert isinstance(conn, Connection)
    conn.path = path
    return conn


def open_writer(path: str) -> Connection:
    """A connection that may write ``path`` (created when it does not exist)."""
    return _connect(path, path, timeout=WRITE_WAIT_S)


def open_reader(path: str) -> Connection:
    """A read-only connection that needs no write access to the file or its folder."""
    if not Path(path).is_file():
        raise StoreError(f"{path}: no such database")
    uri = f"file:{quote(str(Path(path).resolve()))}"
    conn = _connect(f"{uri}?mode=ro", path, timeout=READ_WAIT_S, uri=True)
    try:
        conn.execute("PRAGMA user_version").fetchone()
    except SqliteError as exc:
        conn.close()
        text = str(exc.cause).lower()
        if not isinstance(exc.cause, sqlite3.OperationalError) or "lock" in text:
            raise
        # A WAL file whose -shm cannot be created here: read it as an immutable file.
        conn = _connect(f"{uri}?immutable=1", path, timeout=READ_WAIT_S, uri=True)
    return conn


class Transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT``, or ``ROLLBACK`` on any exception. Inside an
    open transaction it does nothing: the outer one commits or rolls back the whole."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self.conn = conn
        self.outer = False

    def __enter__(self) -> sqlite3.Connection:
        if not self.conn.in_transaction:
            with writing():
                self.conn.execute("BEGIN IMMEDIATE")
            self.outer = True
        return self.conn

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if not self.outer:
            return
        if exc_type is None:
            with writing():
                self.conn.execute("COMMIT")
            return
        with contextlib.suppress(sqlite3.Error, StoreError):
            self.conn.execute("ROLLBACK")
        if isinstance(exc, SqliteError) and isinstance(exc.cause, sqlite3.OperationalError):
            raise write_fault(exc) from None


@contextlib.contextmanager
def writing() -> Iterator[None]:
    """Statements that write: a failure is :func:`write_fault`'s line."""
    try:
        yield
    except SqliteError as exc:
        raise write_fault(exc) from None
