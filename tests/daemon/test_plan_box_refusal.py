"""A campaign whose plan moves out of the workspace box on the way is refused where its
plan is made, before any motion: one line naming the first such move — from which pose
to which, numbered as the engine numbers them — and by how far; exit 2 (a refused
configuration), nothing stored. ``cellcal plan`` still lists those moves (exit 0)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from cellcal.campaign.runner import plan_campaign
from cellcal.config import load_config
from cellcal.errors import CampaignError
from tests.conftest import TRACKER_CELL
from tests.inprocess import cellcal

#: A box around the bundled tracker cell's cube and regions, 20 mm to spare: some of
#: its plan's moves swing out of it on the way (tests/test_motion_gate.py).
LO, HI = [330.0, -945.0, 298.0], [1149.0, 1032.0, 1139.0]


@pytest.fixture
def tight_cell(tmp_path: Path) -> Path:
    text = TRACKER_CELL.read_text().replace(
        "[campaign]\n", f"[campaign]\nworkspace_min_mm = {LO}\nworkspace_max_mm = {HI}\n"
    )
    cell = tmp_path / "cell.toml"
    cell.write_text(text)
    return cell


def _first_leaving(cell: Path) -> dict[str, object]:
    """The first move ``cellcal plan`` lists as leaving the box."""
    run = cellcal("plan", "--config", cell, "--json")
    assert run.returncode == 0, run.stderr
    leaving = json.loads(run.stdout)["moves_leaving_box"]
    assert leaving, "the tight box should make some move leave it"
    first: dict[str, object] = leaving[0]
    return first


def _named_move(first: dict[str, object]) -> str:
    k = int(str(first["idx"]))
    start = "home (robot.home_deg)" if k == 0 else f"pose {k - 1}"
    return f"from {start} to pose {k} leaves the workspace box by {first['excess_mm']:.1f} mm"


@pytest.mark.timeout(120)
def test_run_refuses_the_campaign_before_any_motion(tight_cell: Path, tmp_path: Path) -> None:
    first = _first_leaving(tight_cell)
    db = tmp_path / "refused.db"
    run = cellcal("run", "--mock", "--config", tight_cell, "--db", db)
    assert run.returncode == 2, (run.stdout, run.stderr)
    line = run.stderr.strip().splitlines()[-1]
    assert line.startswith("cellcal: error: the plan's joint move "), line
    assert _named_move(first) in line, (first, line)
    assert "workspace_min_mm" in line and "\n" not in line
    assert run.stdout == ""
    # Nothing was started: no campaign, no pose (the run lock leaves no empty file).
    if db.exists() and db.stat().st_size:
        with sqlite3.connect(db) as conn:
            assert conn.execute("SELECT COUNT(*) FROM campaigns").fetchone() == (0,)


@pytest.mark.timeout(120)
def test_the_service_refuses_to_queue_it(tight_cell: Path) -> None:
    """The service plans a start with :func:`plan_campaign` (an ``invalid-params``
    refusal of ``POST /v1/campaigns``): the same line, before anything is queued."""
    first = _first_leaving(tight_cell)
    with pytest.raises(CampaignError) as info:
        plan_campaign(load_config(str(tight_cell)))
    assert _named_move(first) in str(info.value)


@pytest.mark.timeout(120)
def test_the_bundled_cell_is_not_refused() -> None:
    """Its wide box holds every move: planned as before."""
    plan, _ = plan_campaign(load_config(str(TRACKER_CELL)))
    assert len(plan.poses) > 100
