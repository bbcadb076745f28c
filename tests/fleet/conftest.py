"""The fleet tests' PostgreSQL server (one per worker of the parallel run, a database per
test) and cells' campaign databases to replicate (small mock campaigns, made once per
worker)."""

from __future__ import annotations

import itertools
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import small_tracker_file
from tests.fleet.pg_server import PgServer
from tests.inprocess import cellcal

_names = itertools.count()


@pytest.fixture(scope="session")
def pg(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PgServer]:
    """A running server, and libpq's password file for it in ``PGPASSFILE``."""
    pytest.importorskip("psycopg")
    server = PgServer()
    server.start()
    before = os.environ.get("PGPASSFILE")
    os.environ["PGPASSFILE"] = str(server.passfile(tmp_path_factory.mktemp("pgpass")))
    try:
        yield server
    finally:
        if before is None:
            os.environ.pop("PGPASSFILE", None)
        else:
            os.environ["PGPASSFILE"] = before
        server.remove()


@pytest.fixture
def fleet_db(pg: PgServer) -> str:
    """A fresh fleet database on the server; its URL."""
    name = f"fleet_{next(_names)}"
    pg.create_database(name)
    return pg.url(name)


def cell_config(folder: Path, name: str, url: str, line: str = "line3") -> Path:
    """The small tracker cell with ``[fleet]`` to ``url`` and its database beside it."""
    fleet = {"database": url, "cell": name, "line": line}
    storage = {"database": f"{name}.db"}
    return small_tracker_file(folder, name, [2, 2, 3], 4, 4, storage=storage, fleet=fleet)


@pytest.fixture(scope="session")
def campaigns(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cell's database with a calibration and a check (copied by each test)."""
    folder = tmp_path_factory.mktemp("cell")
    config = cell_config(folder, "template", "postgresql://nobody@127.0.0.210:1/none")
    for args in (("run",), ("check",)):
        done = cellcal(*args, "--mock", "--config", config)
        assert done.returncode == 0, done.stderr[-2000:]
    return folder / "template.db"


def make_cell(folder: Path, campaigns: Path, name: str, url: str) -> Path:
    """A cell of its own name: the template's campaigns, its config to ``url``."""
    config = cell_config(folder, name, url)
    shutil.copyfile(campaigns, folder / f"{name}.db")
    return config
