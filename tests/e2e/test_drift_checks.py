"""Checks between calibrations on the simulated cell (tracker alone, a small cube): the
done-when sequence of the issue — calibrate, check (ok), change the cell, check
(recalibrate, its cause named, exit 4), recalibrate, check (ok) — and what the database
keeps of it (the models' validity, the checks); each change the simulation offers is
named by the check."""

from __future__ import annotations

import json
import sqlite3
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from tests.conftest import small_tracker_file
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(300)]

ROOT = Path(__file__).resolve().parents[2]


def _cell(folder: Path, name: str, change: dict[str, Any] | None = None) -> Path:
    more = {"simulation": {"change": change}} if change else {}
    return small_tracker_file(folder, name, [3, 3, 4], 5, 8, **more)


def _copy(calibrated: tuple[Path, Path], folder: Path) -> tuple[Path, Path]:
    """The calibrated cell's configuration, and a copy of its database in ``folder``."""
    config, source = calibrated
    db = folder / "cell.db"
    db.write_bytes(source.read_bytes())
    return config, db


def _check(config: Path, db: Path, *more: object) -> tuple[int, dict[str, Any]]:
    done = cellcal("check", "--mock", "--config", config, "--db", db, "--json", *more)
    assert done.returncode in (0, 4), done.stderr[-2000:]
    said = done.stderr.splitlines()  # its progress, in the check's words
    assert said[0].endswith(": planning the poses and starting the devices' twins…"), said
    assert said[-1] == "every pose stored: comparing the errors with the model's limits…", said
    return done.returncode, json.loads(done.stdout)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A calibrated small cell: its configuration and its database (campaign 1)."""
    folder = tmp_path_factory.mktemp("drift")
    config, db = _cell(folder, "cell"), folder / "cell.db"
    done = cellcal("run", "--mock", "--config", config, "--db", db)
    assert done.returncode == 0, done.stderr[-2000:]
    return config, db


def test_calibrate_check_change_check_recalibrate_check(
    calibrated: tuple[Path, Path], tmp_path: Path
) -> None:
    config, db = _copy(calibrated, tmp_path)
    code, ok = _check(config, db)
    assert code == 0 and ok["verdict"] == "ok" and ok["cause"] is None
    for key in ("campaign_id", "kind", "model", "n_poses", "rms_mm", "max_mm", "limit_mm"):
        assert key in ok
    assert ok["kind"] == "check" and ok["n_poses"] == 12 == len(ok["errors_mm"])
    assert ok["model"] == "model 1 (campaign 1)" and ok["model_id"] == 1
    assert ok["rms_mm"] < ok["warning_mm"] < ok["limit_mm"]
    # the limit comes from the model's own uncertainty: a few hundredths of a mm
    assert 0.005 < ok["limit_mm"] < 0.05

    changed = _cell(tmp_path, "changed", {"joint_offset_deg": [0.0, 0.02, 0.0, 0.0, 0.0, 0.0]})
    code, bad = _check(changed, db)
    assert code == 4 and bad["verdict"] == "recalibrate"
    assert bad["rms_mm"] > 3 * bad["limit_mm"]
    assert bad["cause"].startswith("joint 2 offset +0.0")
    assert bad["causes"][0]["values"]["theta2"] == pytest.approx(0.02, abs=0.001)

    # the failed check ended the model: no current model to check against
    again = cellcal("check", "--mock", "--config", changed, "--db", db)
    assert again.returncode == 2
    assert again.stderr.strip() == (
        f"cellcal: error: no current model in {db}: model 1 was ended by check campaign 3 "
        "(recalibrate); calibrate (cellcal run), or check against a model file with "
        "--model FILE"
    )

    done = cellcal("run", "--mock", "--config", changed, "--db", db)
    assert done.returncode == 0, done.stderr[-2000:]
    code, after = _check(changed, db)
    assert code == 0 and after["verdict"] == "ok" and after["model_id"] == 2

    listed = cellcal("models", "--cell", "--db", db, "--json")
    assert listed.returncode == 0, listed.stderr
    models = json.loads(listed.stdout)["models"]
    assert [(m["id"], m["campaign_id"], m["current"]) for m in models] == [
        (1, 1, False),
        (2, 4, True),
    ]
    assert models[0]["ended_by"] == "check campaign 3 (recalibrate)"
    assert models[0]["valid_until"] <= models[1]["valid_from"]
    assert [c["verdict"] for c in models[0]["checks"]] == ["ok", "recalibrate"]
    assert [c["verdict"] for c in models[1]["checks"]] == ["ok"]
    text = cellcal("models", "--cell", "--db", db)
    assert "ended by check campaign 3 (recalibrate)" in text.stdout
    assert "current" in text.stdout.splitlines()[3]

    conn = sqlite3.connect(db)
    kinds = conn.execute("SELECT id, kind FROM campaigns ORDER BY id").fetchall()
    text, digest = conn.execute("SELECT model_toml, digest FROM models WHERE id = 1").fetchone()
    conn.close()
    assert kinds == [
        (1, "calibration"),
        (2, "check"),
        (3, "check"),
        (4, "calibration"),
        (5, "check"),
    ]

    # the reports: the check's verdict and cause, the calibration's model and its checks
    assert cellcal("report", "--db", db, "--campaign", 3, "--out", tmp_path / "r3").returncode == 0
    page = (tmp_path / "r3" / "index.html").read_text()
    assert "verdict: recalibrate" in page and "cause: joint 2 offset +0.0" in page
    assert f"model 1 (campaign 1), digest {digest}" in page and 'id="drift-chart"' in page
    summary = json.loads((tmp_path / "r3" / "summary.json").read_text())["summary"]
    assert summary["verdict"] == "recalibrate" and summary["model_id"] == 1
    assert cellcal("report", "--db", db, "--campaign", 1, "--out", tmp_path / "r1").returncode == 0
    page = (tmp_path / "r1" / "index.html").read_text()
    assert "<h2>Checks of the model</h2>" in page
    table = page[page.index('id="drift-checks"') :]
    # its two checks under the header, not the later model's
    assert table[: table.index("</table>")].count("<tr>") == 3

    # a compensation names the model it used, by the digest the database knows it by
    model = tmp_path / "model.toml"
    model.write_text(text)
    targets = ROOT / "examples" / "compensate-targets.csv"
    joints = tmp_path / "joints.csv"
    done = cellcal("compensate", "--model", model, "--targets", targets, "--out", joints, "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["model_digest"] == digest


CHANGES = [
    ({"joint_offset_deg": [0.0, 0.0, 0.015, 0.0, 0.0, 0.0]}, "theta3", {"theta3": 0.015}),
    ({"base_shift_mm": [0.15, -0.1, 0.0]}, "frame_shift", {"x_mm": 0.15, "y_mm": -0.1}),
    ({"link_mm": {"a2": 0.1}}, "a2", {"a2": 0.1}),
    # the arm 10 °C warmer all along: 0.1 mm more reach, about 50 ppm of its 2 m
    ({"thermal_mm_per_c": 0.01, "temperature_c": [[0, 30]]}, "growth", {"ppm": 50.0}),
]


@pytest.mark.parametrize(("change", "name", "values"), CHANGES, ids=[c[1] for c in CHANGES])
def test_each_change_is_named(
    calibrated: tuple[Path, Path],
    tmp_path: Path,
    change: dict[str, Any],
    name: str,
    values: dict[str, float],
) -> None:
    _, db = _copy(calibrated, tmp_path)
    model = tmp_path / "model.toml"
    conn = sqlite3.connect(db)
    (text,) = conn.execute("SELECT model_toml FROM models WHERE id = 1").fetchone()
    conn.close()
    model.write_text(text)
    code, out = _check(_cell(tmp_path, "changed", change), db, "--model", model)
    assert code == 4 and out["verdict"] == "recalibrate"
    assert out["model_id"] == 1  # the file is the database's model 1: it is ended,
    assert out["model"] == "model 1 (campaign 1)"  # and named so
    cause = out["causes"][0]
    assert cause["name"] == name, out["cause"]
    for key, value in values.items():
        assert cause["values"][key] == pytest.approx(value, abs=0.1 * abs(value))


def test_run_kind_check_exits_4_and_a_model_without_covariance_is_refused(
    calibrated: tuple[Path, Path], tmp_path: Path
) -> None:
    config, db = _copy(calibrated, tmp_path)
    changed = _cell(tmp_path, "changed", {"joint_offset_deg": [0.02, 0, 0, 0, 0, 0]})
    done = cellcal("run", "--mock", "--config", changed, "--db", db, "--kind", "check")
    assert done.returncode == 4, done.stderr[-2000:]
    assert "verdict: recalibrate" in done.stdout
    # joint 1 turns about the base's own axis: the check says it cannot tell them apart
    assert "joint 1 offset +0.0" in done.stdout and "cannot tell them apart" in done.stdout
    conn = sqlite3.connect(db)
    (text,) = conn.execute("SELECT model_toml FROM models WHERE id = 1").fetchone()
    conn.close()
    doc = tomllib.loads(text)
    del doc["fit"]["covariance"]
    old = tmp_path / "old.toml"
    old.write_text(tomli_w.dumps(doc))
    refused = cellcal("check", "--mock", "--config", config, "--db", db, "--model", old)
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "no covariance of its parameters" in refused.stderr


def test_a_model_of_another_robot_and_an_empty_file_are_refused_before_any_motion(
    calibrated: tuple[Path, Path], tmp_path: Path
) -> None:
    """A database or a model file of another cell (here the cell's model with its upper
    arm 100 mm longer, as another robot's would be) is refused at planning, and the
    database's model stays current; an empty --model file is refused, not read as "no
    file" (which checked the current model instead)."""
    config, db = _copy(calibrated, tmp_path)
    conn = sqlite3.connect(db)
    (text,) = conn.execute("SELECT model_toml FROM models WHERE id = 1").fetchone()
    conn.close()
    doc = tomllib.loads(text)
    doc["joint"][1]["a"] += 100.0
    other = tmp_path / "other.toml"
    other.write_text(tomli_w.dumps(doc))
    refused = cellcal("check", "--mock", "--config", config, "--db", db, "--model", other)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.splitlines()[-1]
    assert line.startswith("cellcal: error: the model is not a calibration of this cell's robot")
    assert "a calibration moves it at most 10 mm" in line
    empty = tmp_path / "empty.toml"
    empty.write_text("\n")
    refused = cellcal("check", "--mock", "--config", config, "--db", db, "--model", empty)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert (
        refused.stderr
        == f"cellcal: error: --model {empty}: an empty file, not a calibrated model\n"
    )
    refused = cellcal("check", "--mock", "--config", config, "--db", db, "--model", "")
    assert refused.returncode == 2 and "give the calibrated model's file" in refused.stderr
    conn = sqlite3.connect(db)
    rows = conn.execute("SELECT COUNT(*) FROM campaigns WHERE kind = 'check'").fetchone()
    ended = conn.execute("SELECT ended_by FROM models WHERE id = 1").fetchone()
    conn.close()
    assert rows == (0,) and ended == (None,)  # nothing moved, nothing recorded
