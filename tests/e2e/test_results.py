"""Campaign results: refused analyses keep every sample and exit 3; the report folder and
the campaign list read the database (read-only), and calibrate reads the report back."""

from __future__ import annotations

import json
import os
import sqlite3
import stat
import subprocess

import numpy as np
import pytest

from cellcal.campaign.runner import resume_campaign, start_campaign
from cellcal.cli import main
from cellcal.errors import AcceptanceError
from cellcal.mocks.simulated_cell import SimulatedCell
from tests.bundled_campaign import bundled_database
from tests.conftest import TRACKER_CELL, tracker_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``cellcal ARGS`` in the test's process (tests/inprocess.py)."""
    return cellcal(*args)


@pytest.fixture
def static_tracker(monkeypatch):
    """The tracker twin measures a reflector that never moves (the target does not follow
    the robot), as a tracker aimed at a fixed nest would."""
    real = SimulatedCell.true_position

    def fixed(self, sensor, q=None):
        p = real(self, sensor, q)
        return np.array([1500.0, 200.0, 300.0]) if sensor == "tracker" else p

    monkeypatch.setattr(SimulatedCell, "true_position", fixed)


def test_a_target_that_does_not_follow_the_robot_is_refused_and_kept(tmp_path, static_tracker):
    config = tracker_cell()
    db = str(tmp_path / "c.db")
    with pytest.raises(AcceptanceError) as info:
        start_campaign(config, db, config_path=None, mock=True)
    assert info.value.check == "target does not follow the robot"
    assert "every sample is stored" in str(info.value)
    conn = sqlite3.connect(db)
    status, n_poses = conn.execute("SELECT status, n_poses FROM campaigns").fetchone()
    assert status == "refused"
    assert conn.execute("SELECT COUNT(*) FROM poses").fetchone()[0] == n_poses
    assert conn.execute("SELECT COUNT(*) FROM calibrations").fetchone()[0] == 0
    assert conn.execute("SELECT COUNT(*) FROM registrations").fetchone()[0] == 0
    conn.close()
    # --accept analyses it anyway and records why.
    with pytest.raises(AcceptanceError):
        resume_campaign(db, 1)
    out = resume_campaign(db, 1, accept=True)
    assert out.summary is not None
    assert any("accepted despite" in w for w in out.summary.calibration.warnings)


def test_run_exits_3_with_one_line(tmp_path, static_tracker, capsys):
    with pytest.raises(SystemExit) as info:
        main(["run", "--mock", "--config", str(TRACKER_CELL), "--db", str(tmp_path / "c.db")])
    assert info.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("cellcal: refused: target does not follow the robot")


@pytest.fixture(scope="module")
def finished(request, tmp_path_factory):
    """The bundled cell's whole campaign, tracker and camera rig (GigE Vision twins that
    render what each camera sees): README's, when its test runs in this session, else
    run here (tests/bundled_campaign.py); its report folder written by `cellcal report`,
    and what `run --json` would have said, from the report's summary."""
    folder = tmp_path_factory.mktemp("finished")
    db, _ = bundled_database(request, folder)
    res = _cli("report", "--db", str(db), "--out", str(folder / "r"), "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads((folder / "r" / "summary.json").read_text())
    return folder, {**summary["summary"], "n_poses": summary["n_poses"]}


@pytest.mark.timeout(1500)  # the first to ask runs the rig campaign
def test_the_rig_measures_every_pose_it_sees_with_an_honest_covariance(finished):
    folder, run = finished
    conn = sqlite3.connect(folder / "c.db")
    # every rig sample carries its covariance and the target's orientation; every tracker
    # sample (line protocol version 2, negotiated with the twin) its covariance and air
    n, cov, ori = conn.execute(
        "SELECT COUNT(*), COUNT(cov_xx), COUNT(ori_w) FROM samples WHERE sensor = 'rig'"
    ).fetchone()
    assert n > 0 and cov == ori == n
    n, cov, ori, air = conn.execute(
        "SELECT COUNT(*), COUNT(cov_xx), COUNT(ori_w), COUNT(temperature_c) FROM samples "
        "WHERE sensor = 'tracker'"
    ).fetchone()
    assert n > 0 and cov == air == n and ori == 0
    sigma = np.sqrt(conn.execute("SELECT cov_xx, cov_yy, cov_zz FROM samples WHERE sensor = 'rig'")
                    .fetchall())  # fmt: skip
    assert 0.003 < float(np.median(sigma)) < 0.05  # mm per sample, 1σ
    # the rig sees the cube; poses it does not see are kept without it, each said once
    kinds = dict(conn.execute("SELECT kind, COUNT(*) FROM events GROUP BY kind").fetchall())
    rig_poses = conn.execute(
        "SELECT COUNT(*) FROM pose_stats s JOIN poses p ON p.id = s.pose_id "
        "WHERE s.sensor = 'rig' AND p.role = 'calibration'"
    ).fetchone()[0]
    assert rig_poses == run["n_calibration_poses"] == 80
    n_rig = conn.execute("SELECT COUNT(*) FROM pose_stats WHERE sensor = 'rig'").fetchone()[0]
    assert kinds.get("no-target", 0) == run["n_poses"] - n_rig
    # every rig pose has its 20 samples (a set that misses is taken again), or a
    # short-series event that says why not
    short = conn.execute(
        "SELECT p.idx FROM pose_stats s JOIN poses p ON p.id = s.pose_id "
        "WHERE s.sensor = 'rig' AND s.n != 20 AND NOT EXISTS (SELECT 1 FROM events e "
        "WHERE e.kind = 'short-series' AND e.pose_idx = p.idx AND e.message LIKE '%, rig: %')"
    ).fetchall()
    assert short == []
    # registered like the tracker: a few µm above the tracker's residual, under 0.03 mm
    reg = {r["sensor"]: r for r in run["registrations"]}
    assert reg["tracker"]["rms_calibrated_mm"] < reg["rig"]["rms_calibrated_mm"] < 0.03
    # after registration the rig agrees with the tracker as its covariance says
    (agree,) = run["agreements"]
    assert agree["sensor"] == "rig" and agree["n"] == n_rig
    assert 0.5 < agree["chi2_per_dof"] < 2.0
    # one fused point per pose, with both sensors where the rig measured
    rows = conn.execute("SELECT sensors, mahalanobis2 FROM fused").fetchall()
    assert len(rows) == run["n_poses"] == run["n_fused"]
    assert sum(sorted(json.loads(s)) == ["rig", "tracker"] for s, _ in rows) == n_rig
    conn.close()


@pytest.mark.timeout(1500)  # the first to ask runs the rig campaign
def test_report_folder_reads_back_to_the_same_calibration(finished):
    folder, run = finished
    rep = folder / "r"
    names = {p.name for p in rep.iterdir()}
    assert {"summary.json", "model.toml", "poses.csv", "index.html"} <= names
    assert {"measurements-tracker.csv", "measurements-rig.csv", "validation-tracker.csv"} <= names
    summary = json.loads((rep / "summary.json").read_text())
    res = _cli(
        "calibrate",
        "--model",
        "kuka-kr5-arc",
        "--data",
        str(rep / "measurements-tracker.csv"),
        "--validate",
        str(rep / "validation-tracker.csv"),
        "--json",
    )
    assert res.returncode == 0, res.stderr
    again = json.loads(res.stdout)
    cal = summary["summary"]["calibration"]
    assert again["rms_after_mm"] == pytest.approx(cal["fit_rms_after_mm"], rel=1e-6)
    assert again["identified"] == cal["identified"]
    assert again["validation"]["after"]["rms_mm"] == pytest.approx(run["rms_after_mm"], rel=1e-6)
    # The stored model is the one predict reads.
    assert "cellcal-calibrated-model" in (rep / "model.toml").read_text()
    assert len((rep / "poses.csv").read_text().splitlines()) == run["n_poses"] + 1
    mode = stat.S_IMODE(os.stat(rep / "summary.json").st_mode)
    assert mode & stat.S_IRGRP  # readable by others, like any file the user writes


@pytest.mark.timeout(1500)  # the first to ask runs the rig campaign
def test_report_and_list_on_a_read_only_folder(finished, tmp_path):
    folder, _ = finished
    db = folder / "c.db"
    assert not (folder / "c.db-wal").exists()  # a finished database is one file
    before = {p.name for p in folder.iterdir() if p.name.startswith("c.db")}
    os.chmod(folder, 0o555)
    try:
        res = _cli("campaign", "list", "--db", str(db), "--json")
        assert res.returncode == 0, res.stderr
        rows = json.loads(res.stdout)["campaigns"]
        assert rows[0]["status"] == "complete" and rows[0]["poses_stored"] > 0
        res = _cli("report", "--db", str(db), "--out", str(tmp_path / "r2"))
        assert res.returncode == 0, res.stderr
        # Readers leave nothing behind (root may write anyway: this checks they do not).
        assert {p.name for p in folder.iterdir() if p.name.startswith("c.db")} == before
    finally:
        os.chmod(folder, 0o755)


@pytest.mark.timeout(1500)  # the first to ask runs the rig campaign
def test_campaign_list_text_and_errors(finished, tmp_path):
    folder, run = finished
    res = _cli("campaign", "list", "--db", str(folder / "c.db"))
    assert res.returncode == 0
    line = res.stdout.splitlines()[1]
    assert line.split()[0] == "1" and "complete" in line
    assert f"{run['rms_after_mm']:.4f}" in line
    res = _cli("campaign", "list")
    assert res.returncode == 2 and "--db" in res.stderr
    other = tmp_path / "other.db"
    conn = sqlite3.connect(other)
    conn.execute("CREATE TABLE t (x)")
    conn.execute("PRAGMA user_version = 1")
    conn.commit()
    conn.close()
    for args in (
        ("campaign", "list", "--db", str(other)),
        ("report", "--db", str(other), "--out", str(tmp_path / "r")),
        ("run", "--mock", "--db", str(other)),
    ):
        res = _cli(*args)
        assert res.returncode == 2, (args, res.stderr)
        # the error is one line, the last; `run` says what it is doing before it
        *progress, error = res.stderr.strip().splitlines()
        assert "not a cellcal database" in error or "another program" in error
        assert all(line.startswith("simulated KR 5 arc cell: planning") for line in progress)
        assert len(progress) == (args[0] == "run")
    res = _cli(
        "report", "--db", str(folder / "c.db"), "--campaign", "9", "--out", str(tmp_path / "x")
    )
    assert res.returncode == 2 and "no campaign 9" in res.stderr


def test_a_read_only_database_is_one_line_on_a_new_campaign(tmp_path, monkeypatch):
    """Root can write any file, so the read-only file is SQLite's own: query_only makes
    every write fail with SQLITE_READONLY, as a file without write permission does."""
    from cellcal.errors import UserError
    from cellcal.store import database as store_module

    real_init = store_module.Store.__init__

    def read_only(self, path, **kw):
        real_init(self, path, **kw)
        self.conn.execute("PRAGMA query_only = 1")

    monkeypatch.setattr(store_module.Store, "__init__", read_only)
    config = tracker_cell()
    with pytest.raises(UserError) as info:
        start_campaign(config, str(tmp_path / "c.db"), config_path=None, mock=True)
    text = str(info.value)
    assert "read-only" in text and "\n" not in text


def test_a_disk_that_fills_during_a_campaign_is_one_line_and_keeps_the_poses(tmp_path, monkeypatch):
    from cellcal.errors import UserError
    from cellcal.store import database as store_module

    real_init = store_module.Store.__init__

    def small_disk(self, path, **kw):
        real_init(self, path, **kw)
        if not kw.get("readonly"):
            # SQLite reports SQLITE_FULL, as on a full disk, beyond this many pages.
            self.conn.execute("PRAGMA max_page_count = 60")

    monkeypatch.setattr(store_module.Store, "__init__", small_disk)
    config = tracker_cell()
    db = str(tmp_path / "c.db")
    with pytest.raises(UserError) as info:
        start_campaign(config, db, config_path=None, mock=True)
    text = str(info.value)
    assert "disk is full" in text and "\n" not in text
    conn = sqlite3.connect(db)
    stored = conn.execute("SELECT COUNT(*) FROM poses").fetchone()[0]
    samples = conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
    conn.close()
    assert 0 < stored < 128 and samples == stored * 20  # whole poses, nothing torn
