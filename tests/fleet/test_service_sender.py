"""The cell service replicates by itself (its sender thread): a campaign run while the
fleet's server is down completes as if there were no fleet — the acquisition never
waits for it —, the status shows what waits and the last error, and once the server is
back the waiting rows arrive, each once."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from cellcal.store.outbox import FLEET_TABLES
from tests.daemon.conftest import daemon, folder  # noqa: F401 - the service's fixtures
from tests.fleet.conftest import cell_config
from tests.fleet.pg_server import PgServer
from tests.inprocess import cellcal
from tests.lazy import psycopg

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(240)]


def test_the_service_sends_by_itself_and_waits_out_a_stopped_server(
    pg: PgServer,
    fleet_db: str,
    folder: Path,  # noqa: F811
    daemon: Any,  # noqa: F811
) -> None:
    config = cell_config(folder, "svc", fleet_db)
    d = daemon(folder, None, time_scale=0.0, config=config)
    d.db = folder / "svc.db"  # the configuration's storage.database
    d.extra = []
    pg.stop()
    d.start()
    run = cellcal("campaign", "start", "--socket", d.sock, "--json")
    assert run.returncode == 0, run.stderr
    s = d.until(lambda s: (s.get("campaign") or {}).get("status") == "complete", 120)
    s = d.until(lambda s: (s.get("fleet") or {}).get("last_error") is not None, 60)
    assert s["fleet"]["waiting"] >= 2 and "fleet server" in s["fleet"]["last_error"]
    text = cellcal("campaign", "status", "--socket", d.sock).stdout
    assert "fleet: " in text and "last error: fleet server" in text
    pg.start()
    d.until(lambda s: s["fleet"]["waiting"] == 0 and s["fleet"]["last_error"] is None, 90)
    local = sqlite3.connect(d.db)
    with psycopg.connect(fleet_db) as conn:
        for table in FLEET_TABLES:
            mine = local.execute(f"SELECT count(*) FROM {table}").fetchone()[0]
            theirs = conn.execute(f"SELECT count(*) FROM {table} WHERE cell = 'svc'").fetchone()
            assert theirs == (mine,), table
    local.close()
    status = json.loads(cellcal("fleet", "status", "--config", config, "--json").stdout)
    assert status["waiting"] == 0 and status["sent"]["samples"]["rows"] > 0
    d.stop()
