"""Three cells replicate into one real PostgreSQL while its network is cut in the middle
of a transfer and the server is stopped and restarted: afterwards every row of every
cell is there exactly once (counted, table by table, against each cell's SQLite), a
replay after a crash changes nothing, and what changes later (a new campaign, a model
ended by a failed check) follows."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from cellcal.store.database import Store
from cellcal.store.outbox import FLEET_TABLES
from tests.fleet.conftest import make_cell
from tests.fleet.pg_server import HOST, PROXY_HOST, PgServer
from tests.fleet.proxy import CuttingProxy
from tests.inprocess import cellcal
from tests.lazy import psycopg

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


def _local_counts(db: Path) -> dict[str, int]:
    conn = sqlite3.connect(db)
    try:
        return {t: conn.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in FLEET_TABLES}
    finally:
        conn.close()


def _fleet_counts(url: str, cell: str) -> dict[str, int]:
    with psycopg.connect(url) as conn:
        return {
            t: conn.execute(f"SELECT count(*) FROM {t} WHERE cell = %s", (cell,)).fetchone()[0]
            for t in FLEET_TABLES
        }


def _sync(config: Path) -> tuple[int, str, dict[str, object] | None]:
    done = cellcal("fleet", "sync", "--config", config, "--json")
    return done.returncode, done.stderr, json.loads(done.stdout) if done.stdout else None


def test_three_cells_through_a_cut_network_and_a_restarted_server(
    pg: PgServer, fleet_db: str, campaigns: Path, tmp_path: Path
) -> None:
    proxy = CuttingProxy(PROXY_HOST, (HOST, pg.port))
    try:
        through = fleet_db.replace(f"{HOST}:{pg.port}", f"{PROXY_HOST}:{proxy.port}")
        cells = {name: make_cell(tmp_path, campaigns, name, through) for name in ("a", "b", "c")}
        code, err, out = _sync(cells["a"])
        assert code == 0, err
        assert out is not None and out["sent"] == 3 and out["waiting"] == 0  # 2 campaigns, 1 model

        # the link is cut in the middle of cell b's samples: one line, nothing half-written
        proxy.cut_after = 20_000
        code, err, _ = _sync(cells["b"])
        assert code == 2 and err.count("\n") == 1 and err.startswith("cellcal: error: fleet server")
        status = json.loads(cellcal("fleet", "status", "--config", cells["b"], "--json").stdout)
        assert status["waiting"] > 0 and status["last_error"] is not None
        proxy.cut_after = None
        proxy.listen()

        # the server stops: one line; cell c waits
        pg.stop()
        code, err, _ = _sync(cells["c"])
        assert code == 2 and err.count("\n") == 1 and "fleet server" in err
        pg.start()

        for name in ("a", "b", "c", "a"):  # and cell a again: nothing new, nothing twice
            code, err, out = _sync(cells[name])
            assert code == 0, err
            assert out is not None and out["waiting"] == 0
        for name in cells:
            assert _fleet_counts(fleet_db, name) == _local_counts(tmp_path / f"{name}.db")
        status = json.loads(cellcal("fleet", "status", "--config", cells["b"], "--json").stdout)
        assert status["waiting"] == 0 and status["last_error"] is None
        assert status["sent"]["samples"]["rows"] >= _local_counts(tmp_path / "b.db")["samples"]
    finally:
        proxy.close()


def test_a_replay_changes_nothing_and_later_changes_follow(
    pg: PgServer, fleet_db: str, campaigns: Path, tmp_path: Path
) -> None:
    config = make_cell(tmp_path, campaigns, "d", fleet_db)
    db = tmp_path / "d.db"
    assert _sync(config)[0] == 0
    # a crash after the server committed, before the cell marked it sent: all sent again
    conn = sqlite3.connect(db)
    conn.execute("UPDATE outbox SET sent = NULL")
    conn.commit()
    conn.close()
    code, err, out = _sync(config)
    assert code == 0 and out is not None and out["sent"] == 3, err
    assert _fleet_counts(fleet_db, "d") == _local_counts(db)

    # a failed check ends the model: the check's campaign and the model's end follow
    changed = (
        config.read_text() + "\n[simulation.change]\njoint_offset_deg = [0, 0.02, 0, 0, 0, 0]\n"
    )
    config.write_text(changed)
    done = cellcal("check", "--mock", "--config", config)
    assert done.returncode == 4, done.stderr[-2000:]
    assert _sync(config)[0] == 0
    assert _fleet_counts(fleet_db, "d") == _local_counts(db)
    with psycopg.connect(fleet_db) as pgc:
        row = pgc.execute("SELECT valid_until, ended_by FROM models WHERE cell = 'd'").fetchone()
        kinds = pgc.execute(
            "SELECT kind, count(*) FROM campaigns WHERE cell = 'd' GROUP BY kind ORDER BY kind"
        ).fetchall()
        line = pgc.execute("SELECT line FROM cells WHERE cell = 'd'").fetchone()
    assert row is not None and row[0] is not None and row[1].startswith("check campaign 3")
    assert kinds == [("calibration", 1), ("check", 2)] and line == ("line3",)

    # an event noted after its campaign finished (as an operator's abort is) follows too
    store = Store(db)
    store.add_event(1, "operator", "noted after the end", None)
    store.close()
    assert _sync(config)[0] == 0
    assert _fleet_counts(fleet_db, "d") == _local_counts(db)


def test_a_batch_sends_a_row_that_came_twice_once_as_it_came_last() -> None:
    from cellcal.store.fleet_server import merged
    from cellcal.store.outbox import Rows

    cols = ("id", "valid_until")
    stats = ("pose_id", "sensor", "n")
    out = merged(
        [
            Rows("models", cols, [(1, None), (2, None)]),
            Rows("pose_stats", stats, [(7, "tracker", 20), (7, "rig", 20)]),
            Rows("models", cols, [(1, "2026-11-28")]),
        ]
    )
    assert [(b.table, b.rows) for b in out] == [
        ("models", [(2, None), (1, "2026-11-28")]),
        ("pose_stats", [(7, "tracker", 20), (7, "rig", 20)]),
    ]
