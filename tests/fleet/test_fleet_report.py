"""The fleet's page: across cells of two lines, each robot's current model, its checks and
when the next is due, a cell whose failed check ended its model shown as needing a
calibration, filters by line and cell, fleet.json for other tools; and a cell name sent
from a second campaign database is refused, not mixed in."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.fleet.conftest import cell_config, make_cell
from tests.fleet.pg_server import PgServer
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(180)]


def test_the_fleet_page_across_lines_and_cells(
    pg: PgServer, fleet_db: str, campaigns: Path, tmp_path: Path
) -> None:
    good = make_cell(tmp_path, campaigns, "l1-a", fleet_db)
    bad = cell_config(tmp_path, "l2-b", fleet_db, line="line2")
    shutil.copyfile(campaigns, tmp_path / "l2-b.db")
    bad.write_text(bad.read_text() + "\n[simulation.change]\nbase_shift_mm = [0.3, 0.0, 0.0]\n")
    assert cellcal("check", "--mock", "--config", bad).returncode == 4
    for config in (good, bad):
        sent = cellcal("fleet", "sync", "--config", config)
        assert sent.returncode == 0 and " entries (" in sent.stdout and " rows) sent" in sent.stdout
    again = cellcal("fleet", "sync", "--config", good)
    assert again.stdout.startswith("cell l1-a: 0 entries (0 rows) sent to ")

    out = tmp_path / "fleet"
    done = cellcal("fleet", "report", "--database", fleet_db, "--out", out, "--json")
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    assert doc == json.loads((out / "fleet.json").read_text())
    cells = {c["cell"]: c for c in doc["cells"]}
    assert set(cells) == {"l1-a", "l2-b"}
    a, b = cells["l1-a"], cells["l2-b"]
    assert a["line"] == "line3" and a["model"]["id"] == 1 and a["due"] == "ok"
    assert a["checks"] == 1 and a["last_check"]["verdict"] == "ok"
    assert a["calibrations"][0]["after_mm"] < a["calibrations"][0]["before_mm"] / 5
    assert b["line"] == "line2" and b["model"] is None and b["due"] == "no model"
    # the check that ended the model is shown (the checks of the model it compared with)
    assert b["checks"] == 2 and b["last_check"]["verdict"] == "recalibrate"
    assert b["last_check"]["rms_mm"] > b["last_check"]["limit_mm"]
    page = (out / "index.html").read_text()
    assert "<h2>line2</h2>" in page and "<h2>line3</h2>" in page and "<script" not in page
    assert page.count("<svg") >= 2  # the overview and a cell's drift
    listed = page[page.index('id="calibrations"') :]
    assert listed[: listed.index("</table>")].count("<tr>") == 3  # header, a calibration each

    # a check overdue at a shorter period
    done = cellcal("fleet", "report", "--database", fleet_db, "--out", out, "--json",
                   "--check-every", "1e-9")  # fmt: skip
    assert {c["cell"]: c["due"] for c in json.loads(done.stdout)["cells"]}["l1-a"] == "overdue"
    done = cellcal("fleet", "report", "--database", fleet_db, "--out", out, "--line", "line2",
                   "--json")  # fmt: skip
    assert [c["cell"] for c in json.loads(done.stdout)["cells"]] == ["l2-b"]
    done = cellcal("fleet", "report", "--database", fleet_db, "--out", out, "--cell", "l2-b")
    assert done.stdout.startswith("fleet of 1 cell: 1 needs a check or a calibration now")
    # the fleet's tables read by another program: docs/fleet.md's query through psql
    doc_text = (Path(__file__).resolve().parents[2] / "docs" / "fleet.md").read_text()
    query = doc_text[doc_text.index("SELECT m.cell") : doc_text.index("m.valid_from;") + 13]
    rows = pg.psql(query.replace("\n", " "), fleet_db.rsplit("/", 1)[1]).split()
    assert len(rows) == 1 and rows[0].startswith("l1-a|1|")  # l2-b's model was ended

    done = cellcal("fleet", "report", "--database", fleet_db, "--out", out, "--cell", "zz")
    assert done.returncode == 2 and "no cell of the fleet matches --cell zz" in done.stderr
    done = cellcal("fleet", "report", "--database", fleet_db.replace("@", ":pw@"), "--out", out)
    assert done.returncode == 2 and "a password in the URL" in done.stderr


def test_a_cell_name_from_another_database_is_refused(
    pg: PgServer, fleet_db: str, campaigns: Path, tmp_path: Path
) -> None:
    (tmp_path / "pc1").mkdir()
    first = make_cell(tmp_path / "pc1", campaigns, "same", fleet_db)
    assert cellcal("fleet", "sync", "--config", first).returncode == 0
    (tmp_path / "pc2").mkdir()
    second = make_cell(tmp_path / "pc2", campaigns, "same", fleet_db)
    done = cellcal("fleet", "sync", "--config", second)
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert "cell same is in the fleet already, sent from another campaign database" in done.stderr
    assert cellcal("fleet", "sync", "--config", first).returncode == 0  # its own: fine
