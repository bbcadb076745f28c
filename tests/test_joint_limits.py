"""Joint limits that drive a robot: a model used on a robot (plan, run, campaigns, the
safety gate, compensate) carries finite, plausible limits or is refused with one line
naming the joint; reading a model to predict or calibrate needs none. A resumed campaign
keeps the limits it was started with (issue 29, items 1 and 3)."""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.robot_model import ModelError, model_from_dict, model_to_dict
from cellcal.campaign.runner import start_campaign, stored_campaign
from cellcal.config import with_robot
from cellcal.drivers.safety import GuardedRobot
from cellcal.errors import CampaignError
from cellcal.files.models import load_model
from cellcal.files.urdf import to_urdf
from cellcal.store.database import Store
from tests.conftest import TRACKER_CELL, tracker_cell
from tests.inprocess import cellcal

KR5 = load_model("kuka-kr5-arc").model
JOINTS = "q1,q2,q3,q4,q5,q6\n0,-30,40,0,-20,0\n10,-40,50,5,-30,20\n"


def _model_toml(path: Path, change) -> Path:
    """The KR 5 arc's table with ``change(rows)`` applied, as a model TOML."""
    import tomli_w

    doc = model_to_dict(KR5)
    change(doc["joint"])
    path.write_text(tomli_w.dumps(doc))
    return path


def _no_limits(rows):
    for row in rows:
        row.pop("min", None)
        row.pop("max", None)


def _third_open(rows):
    rows[2].pop("max")


def _huge(rows):
    rows[0]["min"], rows[0]["max"] = -1e9, 1e9


def _twice_around(rows):
    rows[3]["min"], rows[3]["max"] = -720.0, 720.0


def _config(tmp_path: Path, model: Path | str) -> Path:
    """The bundled tracker cell with ``robot.model`` set to ``model``."""
    text = TRACKER_CELL.read_text().replace('model = "kuka-kr5-arc"', f'model = "{model}"', 1)
    out = tmp_path / "cell.toml"
    out.write_text(text)
    return out


def _one_line(run, code: int = 2) -> str:
    """The one error line (``run`` says what it starts first, on a line of its own)."""
    lines = run.stderr.strip().splitlines()
    assert run.returncode == code, run.stderr
    errors = [line for line in lines if line.startswith("cellcal: error: ")]
    assert errors == lines[-1:] and "Traceback" not in run.stderr, run.stderr
    assert len(lines) == 1 or lines[0].endswith(("twins…", "devices…")), run.stderr
    return lines[-1]


CASES = {
    "no min/max": (_no_limits, "joint 1 has no limits"),
    "joint 3 without max": (_third_open, "joint 3 has no upper limit"),
    "limits of 1e9": (_huge, "joint 1's limits"),
    "joint 4 at ±720°": (_twice_around, "joint 4's limits -720..720°"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_plan_refuses_a_model_without_plausible_limits(tmp_path, case):
    change, said = CASES[case]
    model = _model_toml(tmp_path / "robot.toml", change)
    line = _one_line(cellcal("plan", "--config", _config(tmp_path, model)))
    assert said in line and "data sheet" in line, line
    # Reading the same model to predict needs no limits.
    joints = tmp_path / "joints.csv"
    joints.write_text(JOINTS)
    run = cellcal("predict", "--model", model, "--joints", joints)
    assert run.returncode == 0, run.stderr


def test_a_urdf_with_continuous_joints_is_refused_for_a_robot_and_says_how(tmp_path):
    joints = list(KR5.joints)
    joints[1] = replace(joints[1], q_min=-math.inf, q_max=math.inf)
    unbounded = KR5.with_joints(tuple(joints))
    urdf = tmp_path / "kr5.urdf"
    urdf.write_text(to_urdf(unbounded, np.zeros(3)))
    assert 'type="continuous"' in urdf.read_text()
    line = _one_line(cellcal("plan", "--config", _config(tmp_path, urdf)))
    assert "joint 2 has no limits" in line and "<limit lower=" in line, line
    joints = tmp_path / "joints.csv"
    joints.write_text(JOINTS)
    assert cellcal("predict", "--model", urdf, "--joints", joints).returncode == 0


@pytest.mark.timeout(120)
def test_run_refuses_a_model_without_limits_before_anything_moves(tmp_path):
    model = _model_toml(tmp_path / "robot.toml", _no_limits)
    db = tmp_path / "c.db"
    run = cellcal("run", "--mock", "--config", _config(tmp_path, model), "--db", db)
    line = _one_line(run)
    assert "joint 1 has no limits" in line
    assert not db.exists() or Store(str(db), readonly=True).conn.execute(
        "SELECT COUNT(*) FROM poses"
    ).fetchone() == (0,)


def test_the_gate_refuses_a_model_without_limits():
    unbounded = model_from_dict({**model_to_dict(KR5), "joint": _rows_without_limits()})
    with pytest.raises(ModelError, match="joint 1 has no limits"):
        GuardedRobot(object(), unbounded, np.zeros(3), [-1e3] * 3, [1e3] * 3, 0.5)  # type: ignore[arg-type]


def _rows_without_limits():
    rows = model_to_dict(KR5)["joint"]
    _no_limits(rows)
    return rows


# -- a resumed campaign keeps its limits ------------------------------------------------


def _interrupted_campaign(tmp_path: Path, model: Path) -> tuple[str, int]:
    """A campaign on the tracker cell with ``model`` stopped before its first pose."""
    config = with_robot(tracker_cell(), model=str(model))
    db = str(tmp_path / "c.db")
    stop = threading.Event()
    stop.set()
    outcome = start_campaign(config, db, config_path=None, mock=True, stop=stop)
    assert outcome.acquisition.interrupted
    return db, outcome.campaign_id


def _widen(rows, lo=-170.0, hi=170.0, joint=0):
    rows[joint]["min"], rows[joint]["max"] = lo, hi


@pytest.mark.timeout(120)
def test_resume_refuses_a_model_whose_limits_changed(tmp_path):
    model = _model_toml(tmp_path / "robot.toml", lambda rows: None)
    db, cid = _interrupted_campaign(tmp_path, model)
    store = Store(db)
    try:
        stored_campaign(store, cid)  # the same limits: resumable
        # Joint 1 widened from ±155° to ±170°: plausible for a robot, not this one's.
        _model_toml(model, _widen)
        with pytest.raises(CampaignError, match=r"joint 1.*-155\.\.155°.*-170\.\.170°"):
            stored_campaign(store, cid)
    finally:
        store.close()
    line = _one_line(cellcal("run", "--resume", cid, "--db", db))
    assert "joint 1" in line and "started with" in line, line
    # Widened to ±720°: refused too (no robot's range, and not the campaign's).
    _model_toml(model, lambda rows: _widen(rows, -720.0, 720.0, 3))
    line = _one_line(cellcal("run", "--resume", cid, "--db", db))
    assert "joint 4" in line, line
