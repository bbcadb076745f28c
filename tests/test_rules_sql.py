"""One face for the store: ``scripts/check_sql_in_store.py`` refuses SQL outside
``cellcal/store/``, one line per offence, and finds none in cellcal."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKER = ROOT / "scripts" / "check_sql_in_store.py"


def _check(*paths: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(CHECKER), *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def _package(root: Path, files: dict[str, str]) -> Path:
    """A package ``cellcal`` under ``root`` with ``files`` (path → source)."""
    for name, text in files.items():
        path = root / "cellcal" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return root / "cellcal"


#: The store's modules may do all of it.
STORE = {
    "__init__.py": "",
    "store/__init__.py": "",
    "store/database.py": """
        import sqlite3

        def count(conn):
            return conn.execute("SELECT COUNT(*) FROM poses").fetchone()[0]

        def open_it(path):
            conn = sqlite3.connect(path)
            conn.executescript("PRAGMA user_version = 1")
            return conn.cursor()
        """,
    "store/queries.py": """
        def ids(conn):
            conn.executemany("INSERT INTO t VALUES (?)", [(1,)])
        """,
}


def test_sql_outside_the_store_is_one_line_each(tmp_path):
    pkg = _package(
        tmp_path,
        {
            **STORE,
            "reports/folder.py": """
                from cellcal.store.database import count

                def latest(store):
                    return store.conn.execute("SELECT MAX(id) FROM campaigns").fetchone()

                def poses(store):
                    return count(store.conn)  # through the store: fine
                """,
            "commands/export.py": """
                import sqlite3 as db
                from sqlite3 import connect

                def dump(path):
                    conn = db.connect(path)
                    cur = conn.cursor()
                    cur.executemany("INSERT INTO t VALUES (?)", [(1,)])
                    conn.executescript("DELETE FROM t")
                    return connect
                """,
            "campaign/store_writer.py": """
                def load(conn):
                    conn.execute("SELECT 1")
                """,
        },
    )
    out = _check(pkg)
    assert out.returncode == 1, out
    lines = out.stdout.splitlines()
    where = [line.split(": ", 1)[0] for line in lines]
    export = str(pkg / "commands" / "export.py")
    assert where == [
        # named like the store, outside its folder: not the store
        f"{pkg / 'campaign' / 'store_writer.py'}:3",
        f"{export}:3",
        f"{export}:6",
        f"{export}:7",
        f"{export}:8",
        f"{export}:9",
        f"{pkg / 'reports' / 'folder.py'}:5",
    ]
    assert "store.conn.execute() runs SQL" in lines[6]
    assert "db.connect" in lines[2] and "conn.cursor() opens a cursor" in lines[3]
    assert all("outside the store" in line for line in lines)
    names = {Path(w.rsplit(":", 1)[0]).name for w in where}
    assert names == {"export.py", "folder.py", "store_writer.py"}  # the store's: none


def test_a_clean_package_passes(tmp_path):
    pkg = _package(
        tmp_path,
        {
            **STORE,
            "reports/folder.py": """
                import sqlite3

                def latest(store):
                    try:
                        return store.latest_campaign_id()
                    except sqlite3.Error:
                        return None
                """,
        },
    )
    out = _check(pkg)
    assert (out.returncode, out.stdout, out.stderr) == (0, "", "")


def test_a_module_that_does_not_parse_is_an_offence(tmp_path):
    pkg = _package(tmp_path, {"broken.py": "def f(:\n"})
    out = _check(pkg)
    assert out.returncode == 1
    assert out.stdout.startswith(f"{pkg / 'broken.py'}:1: cannot be parsed")


def test_a_missing_path_is_a_usage_error(tmp_path):
    out = _check(tmp_path / "nowhere")
    assert out.returncode == 2 and "no such file or folder" in out.stderr


def test_cellcal_keeps_its_sql_in_the_store():
    out = _check(ROOT / "cellcal")
    assert (out.returncode, out.stdout) == (0, ""), out.stdout
