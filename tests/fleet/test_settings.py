"""Bad fleet settings are one line each, naming the server and what is wrong — a port
nobody listens on, a wrong password, a database that does not exist, a server whose
fleet schema is of another version, a database with any table of another program, a
password in the configuration, no ``[fleet]`` at all — and nothing is written to such a
server; ``fleet report`` refuses a database without the fleet and creates nothing. A
campaign never waits for the fleet: it runs to its end with the server unreachable."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.fleet.conftest import cell_config, make_cell
from tests.fleet.pg_server import HOST, PgServer, free_port
from tests.inprocess import cellcal
from tests.lazy import psycopg

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(120)]


def _refused(config: Path, *words: str) -> str:
    done = cellcal("fleet", "sync", "--config", config)
    assert done.returncode == 2, done.stdout
    line = done.stderr
    assert line.count("\n") == 1 and line.startswith("cellcal: error: "), line
    for w in words:
        assert w in line, line
    return line


def test_bad_settings_are_one_line(
    pg: PgServer, fleet_db: str, campaigns: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    port = free_port(HOST)
    nobody = make_cell(tmp_path, campaigns, "p", pg.url("fleet", port=port))
    _refused(nobody, f"fleet server postgresql://fleet_admin@{HOST}:{port}/fleet", "refused")
    missing = make_cell(tmp_path, campaigns, "m", pg.url("no_such_database"))
    _refused(missing, 'database "no_such_database" does not exist')

    ok = make_cell(tmp_path, campaigns, "w", fleet_db)
    monkeypatch.setenv("PGPASSFILE", str(pg.passfile(tmp_path, "not-the-password")))
    _refused(ok, "password authentication failed", "PGPASSFILE")
    monkeypatch.setenv("PGPASSFILE", str(tmp_path / "none"))
    _refused(ok, "no password supplied", "PGPASSFILE")
    monkeypatch.undo()
    status = json.loads(cellcal("fleet", "status", "--config", ok, "--json").stdout)
    assert "no password supplied" in status["last_error"] and status["waiting"] == 3
    (tmp_path / "open").mkdir()
    shared = pg.passfile(tmp_path / "open")
    shared.chmod(0o644)  # libpq ignores it, with a warning line of its own: said in one
    monkeypatch.setenv("PGPASSFILE", str(shared))
    _refused(ok, f"the password file {shared} may be read by others (mode 0644)", "chmod 600")
    monkeypatch.undo()

    # a server of another fleet schema version, and a database of another program
    assert cellcal("fleet", "sync", "--config", ok).returncode == 0
    with psycopg.connect(fleet_db, autocommit=True) as conn:
        conn.execute("UPDATE cellcal_fleet SET value = '2' WHERE key = 'schema_version'")
        before = conn.execute("SELECT count(*) FROM campaigns").fetchone()
    assert cellcal("check", "--mock", "--config", ok).returncode == 0  # a new campaign waits
    _refused(ok, "its fleet schema is version 2, this cellcal writes version 1")
    with psycopg.connect(fleet_db) as conn:
        assert conn.execute("SELECT count(*) FROM campaigns").fetchone() == before
    pg.create_database("someone_elses")
    pg.psql("CREATE TABLE campaigns (x int)", "someone_elses")
    other = make_cell(tmp_path, campaigns, "o", pg.url("someone_elses"))
    _refused(other, "tables of another program (campaigns; no cellcal_fleet table)")
    # any table of another program, whatever its name, and nothing is created beside it
    pg.create_database("invoicing")
    pg.psql("CREATE TABLE invoices (x int)", "invoicing")
    billing = make_cell(tmp_path, campaigns, "i", pg.url("invoicing"))
    _refused(billing, "tables of another program (invoices; no cellcal_fleet table)")
    tables = "SELECT table_name FROM information_schema.tables WHERE table_schema = 'public'"
    assert pg.psql(tables, "invoicing").split() == ["invoices"]
    # the report reads: a database without the fleet (a mistyped name) is refused, and
    # nothing is created in it
    pg.create_database("empty_one")
    for name, said in (
        ("empty_one", "no fleet in this database (no cellcal_fleet table): check its name"),
        ("invoicing", "tables of another program (invoices; no cellcal_fleet table)"),
    ):
        done = cellcal("fleet", "report", "--database", pg.url(name), "--out", tmp_path / "r")
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert said in done.stderr
    assert pg.psql(tables, "empty_one").split() == []
    assert pg.psql(tables, "invoicing").split() == ["invoices"]


def test_a_password_in_the_configuration_and_no_fleet_are_one_line(tmp_path: Path) -> None:
    config = cell_config(tmp_path, "x", "postgresql://fleet_admin:secret@127.0.0.210:5432/fleet")
    done = cellcal("fleet", "status", "--config", config)
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert "fleet.database: a password in the URL" in done.stderr and "secret" not in done.stderr
    plain = tmp_path / "plain.toml"
    plain.write_text(re.sub(r"(?s)\[fleet\].*", "", config.read_text()))
    done = cellcal("fleet", "sync", "--config", plain)
    assert done.returncode == 2 and "no [fleet] table" in done.stderr


def test_a_campaign_never_waits_for_the_fleet(tmp_path: Path) -> None:
    """The server is unreachable (a port nobody listens on): the campaign runs, its
    rows wait in the outbox."""
    config = cell_config(tmp_path, "away", f"postgresql://u@{HOST}:{free_port(HOST)}/fleet")
    done = cellcal("run", "--mock", "--config", config)
    assert done.returncode == 0, done.stderr[-2000:]
    status = json.loads(cellcal("fleet", "status", "--config", config, "--json").stdout)
    assert status["waiting"] == 2 and status["last_attempt"] is None  # a campaign, a model
