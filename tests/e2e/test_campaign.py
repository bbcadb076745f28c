"""Whole campaigns in mock mode: through the API, the CLI, and a real process killed
with SIGKILL at several points and resumed."""

from __future__ import annotations

import json
import math
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cellcal.campaign.runner import resume_campaign, start_campaign
from cellcal.config import with_robot
from cellcal.errors import CampaignError
from cellcal.files.models import load_model
from cellcal.mocks.simulated_cell import SimulatedCell
from tests.conftest import TRACKER_CELL, tracker_cell
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow]


def test_mock_campaign_recovers_the_injected_errors(tmp_path):
    config = tracker_cell()
    out = start_campaign(config, str(tmp_path / "c.db"), config_path=None, mock=True)
    s = out.summary
    assert s is not None and s.n_calibration == 80
    # Validation poses, measured by the tracker: far better than the nominal model.
    assert s.validation_after.rms < 0.03
    assert s.improvement_pct > 90
    assert s.inside.after.rms < s.inside.before.rms / 10
    assert s.outside.after.rms < s.outside.before.rms / 10
    # The identified corrections are the injected ones (d3 carries d2 too: axes 2 ∥ 3).
    nominal = load_model("kuka-kr5-arc").model
    truth = SimulatedCell(config, nominal).model
    checked = 0
    for p in s.calibration.parameters:
        if not p.identified or p.kind == "target_offset":
            continue
        j = p.joint - 1
        true = getattr(truth.joints[j], p.kind) - getattr(nominal.joints[j], p.kind)
        if p.name == "d3":
            true += truth.joints[1].d - nominal.joints[1].d
        true = math.degrees(true) if p.unit == "deg" else true
        assert abs(p.value - true) < 5 * p.std + 1e-4, p.name
        checked += 1
    assert checked == 18
    # The tracker registered to the base; its residual is its noise once calibrated.
    reg = {r.sensor: r for r in s.registrations}
    assert reg["tracker"].rms_calibrated_mm < 0.01 < reg["tracker"].rms_nominal_mm


def test_same_seed_same_campaign_and_resume_refuses_a_complete_one(tmp_path):
    config = tracker_cell()
    a = start_campaign(config, str(tmp_path / "a.db"), config_path=None, mock=True, seed=7)
    b = start_campaign(config, str(tmp_path / "b.db"), config_path=None, mock=True, seed=7)
    assert a.summary.validation_after.rms == b.summary.validation_after.rms
    assert a.plan.digest == b.plan.digest
    c = start_campaign(config, str(tmp_path / "a.db"), config_path=None, mock=True, seed=8)
    assert c.campaign_id == 2  # a rerun is a new campaign in the same file
    assert c.summary.validation_after.rms != a.summary.validation_after.rms
    with pytest.raises(CampaignError, match="already complete"):
        resume_campaign(str(tmp_path / "a.db"), 1)


def _cli(*args):
    """``cellcal ARGS`` in the test's process (tests/inprocess.py): its exit code and
    streams."""
    return cellcal(*args)


def _process(*args, timeout=120):
    """``cellcal ARGS`` in a process of its own."""
    return subprocess.run(
        [sys.executable, "-m", "cellcal", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_run_json_contract(tmp_path):
    rep = tmp_path / "r"
    res = _cli(
        "run", "--mock", "--config", TRACKER_CELL, "--db", tmp_path / "c.db", "--report", rep,
        "--json",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["report"] == str(rep) and (rep / "summary.json").is_file()
    for key in (
        "campaign_id",
        "n_poses",
        "samples_per_pose",
        "sensors",
        "rms_before_mm",
        "rms_after_mm",
        "improvement_pct",
    ):
        assert key in doc
    assert doc["samples_per_pose"] == 20 and doc["sensors"] == ["tracker"]
    assert doc["rms_after_mm"] < doc["rms_before_mm"] / 10
    assert doc["clock_seconds"] >= doc["n_poses"] * 7  # the 7 s dwell, on the clock


def test_run_prints_a_summary_and_each_residual_on_request(tmp_path):
    """The text output is a summary that fits a screen: the headline figures with their
    uncertainty and where the details are; each calibration pose's residual only with
    --residuals (and in the report and --json)."""
    db = tmp_path / "c.db"
    human = _cli("run", "--mock", "--config", TRACKER_CELL, "--db", db)
    assert human.returncode == 0, human.stderr
    out = human.stdout
    lines = out.splitlines()
    assert len(lines) <= 20, out
    assert lines[0].startswith("simulated KR 5 arc cell: campaign 1 complete: 128 poses")
    for said in (
        "registration to the robot base",
        "21 of 27 parameters of the robot and target offset identified (the sensor frame "
        "besides), σ0 ",
        "with equal weights, `plan`'s measure, at the poses as measured)",
        "another campaign would give 0.0",
        "target offset (25.0",
        "left at nominal: theta1, d1, theta6, d6, a6, alpha6 (not identifiable)",
        "inside the cube",
        "outside the cube",
        "% reduction",
        "tracker residual at the 80 calibration poses: RMS 0.00",
        "(each pose: --residuals, or the report)",
        f"database: {db} (campaign 1)",
        f"cellcal report --db {db} --campaign 1 --out DIR",
    ):
        assert said in out, (said, out)
    # the registration's RMS with the nominal geometry, then with the calibrated one
    assert re.search(r"^  tracker +0\.2\d{3} → 0\.00\d{2} mm  \(80 poses; the reference", out, re.M)
    assert out.count(" ± ") >= 3, out  # the frame, the largest corrections, the offset
    assert "by plan index" not in out

    detailed = _cli(
        "run",
        "--mock",
        "--config",
        TRACKER_CELL,
        "--db",
        db,
        "--residuals",
        "--report",
        tmp_path / "r",
    )
    assert detailed.returncode == 0, detailed.stderr
    rows = detailed.stdout.split("(by plan index)")[1].splitlines()[2:]
    assert sum(r.startswith("  ") and len(r.split()) >= 6 for r in rows) == 80, detailed.stdout
    assert f"report: {tmp_path / 'r' / 'index.html'}" in detailed.stdout
    assert (tmp_path / "r" / "index.html").is_file()


def test_run_user_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "[campaign]\ndwel_s = 7\n[[sensor]]\nname='t'\nkind='laser-tracker'\nreference=true\n"
    )
    for args, match in [
        (["run"], "--config FILE, or --mock"),
        (["run", "--config", bad, "--mock"], "campaign.dwel_s: unknown key"),
        (["run", "--resume", "4", "--db", tmp_path / "none.db"], "no such database"),
        (["run", "--mock", "--time-scale", "-1"], "--time-scale"),
        (["run", "--mock", "--time-scale", "nan"], "not a finite number"),
        (["run", "--mock", "--seed", "-1"], "--seed"),
        (["run", "--mock", "--db", tmp_path / "no" / "such" / "c.db"], "does not exist"),
        (["run", "--config", tmp_path / "missing.toml"], "no such file"),
    ]:
        res = _cli(*args)
        assert res.returncode == 2, res.stderr
        assert res.stdout == ""
        assert len(res.stderr.strip().splitlines()) == 1 and match in res.stderr, res.stderr


def _count(db: Path, sql: str) -> int:
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            row = conn.execute(sql).fetchone()
            return int(row[0]) if row and row[0] is not None else 0
        finally:
            conn.close()
    except sqlite3.OperationalError:
        return 0


def _wait_for_poses(db: Path, proc: subprocess.Popen, n: int, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if _count(db, "SELECT COUNT(*) FROM poses") >= n:
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.005)
    raise AssertionError(f"no {n} poses within {timeout} s")


def _check_complete(db: Path, n_poses: int) -> None:
    assert _count(db, "SELECT COUNT(*) FROM poses") == n_poses
    assert _count(db, "SELECT COUNT(DISTINCT idx) FROM poses") == n_poses
    assert _count(db, "SELECT MAX(idx) FROM poses") == n_poses - 1
    assert _count(db, "SELECT COUNT(*) FROM samples") == n_poses * 20  # the tracker alone
    assert _count(db, "SELECT COUNT(*) FROM pose_stats") == n_poses
    orphans = "SELECT COUNT(*) FROM samples WHERE pose_id NOT IN (SELECT id FROM poses)"
    assert _count(db, orphans) == 0
    assert _count(db, "SELECT COUNT(*) FROM campaigns WHERE status = 'complete'") == 1
    assert _count(db, "SELECT COUNT(*) FROM reports") == 1


@pytest.mark.parametrize("kill_after", [1, 37, 90, "all"])
def test_sigkill_at_any_moment_then_resume_loses_nothing(tmp_path, kill_after):
    db = tmp_path / "c.db"
    cmd = [
        sys.executable,
        "-m",
        "cellcal",
        "run",
        "--mock",
        "--config",
        str(TRACKER_CELL),
        "--db",
        str(db),
        "--time-scale",
        "0.002",
        "--json",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        target = 10**6 if kill_after == "all" else kill_after
        if kill_after == "all":
            # Kill as soon as every pose is in: during the analysis, or just after it.
            n = None
            while proc.poll() is None:
                n = n or _count(db, "SELECT n_poses FROM campaigns")
                if n and _count(db, "SELECT COUNT(*) FROM poses") >= n:
                    break
                time.sleep(0.002)
        elif not _wait_for_poses(db, proc, target):
            # It ended by itself before the kill: that is fine only if it completed.
            assert proc.wait(timeout=30) == 0, proc.stderr.read().decode()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        proc.stdout.close()
        proc.stderr.close()
    n_poses = _count(db, "SELECT n_poses FROM campaigns")
    stored = _count(db, "SELECT COUNT(*) FROM poses")
    assert _count(db, "SELECT COUNT(DISTINCT idx) FROM poses") == stored
    if _count(db, "SELECT COUNT(*) FROM campaigns WHERE status = 'complete'") == 1:
        _check_complete(db, n_poses)  # it finished before the kill landed
        return
    res = _cli("run", "--resume", "1", "--db", db, "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["campaign_id"] == 1
    _check_complete(db, n_poses)


def test_sigterm_ends_cleanly_and_resumes(tmp_path):
    db = tmp_path / "c.db"
    cmd = [
        sys.executable,
        "-m",
        "cellcal",
        "run",
        "--mock",
        "--config",
        str(TRACKER_CELL),
        "--db",
        str(db),
        "--time-scale",
        "0.002",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for_poses(db, proc, 5)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert "resume with: cellcal run --resume 1" in err
    assert _count(db, "SELECT COUNT(*) FROM campaigns WHERE status = 'interrupted'") == 1
    res = _cli("run", "--resume", "1", "--db", db)
    assert res.returncode == 0, res.stderr
    _check_complete(db, _count(db, "SELECT n_poses FROM campaigns"))
    np.testing.assert_equal(_count(db, "SELECT COUNT(*) FROM events WHERE kind = 'resumed'"), 1)


def test_refusals_before_anything_is_written(tmp_path):
    config = tracker_cell()
    db = tmp_path / "c.db"
    small = config.model_copy(
        update={"campaign": config.campaign.model_copy(update={"grid": [2, 2, 2]})}
    )
    with pytest.raises(CampaignError, match=r"8 calibration poses give 24 equations"):
        start_campaign(small, str(db), config_path=None, mock=True)
    from cellcal.errors import DeviceError

    with pytest.raises(DeviceError, match=r"robot\.address is empty"):
        start_campaign(config, str(db), config_path=None, mock=False)
    simulated = with_robot(config, driver="simulated")
    with pytest.raises(DeviceError, match="needs --mock"):
        start_campaign(simulated, str(db), config_path=None, mock=False)
    assert not db.exists() or _count(db, "SELECT COUNT(*) FROM campaigns") == 0


def test_one_run_per_database(tmp_path):
    import os

    from cellcal.campaign.locks import RunLock

    db = str(tmp_path / "c.db")
    config = tracker_cell()
    who = rf"in use by cellcal daemon \(pid {os.getpid()}\)"
    with RunLock(db, "cellcal daemon"), pytest.raises(CampaignError, match=who):
        start_campaign(config, db, config_path=None, mock=True)
    with RunLock(db) as lock:  # free again; it remembers who held it last
        assert lock.previous == f"cellcal daemon (pid {os.getpid()})"


def test_device_fault_is_one_line_with_a_resume_hint_and_resumes(tmp_path, monkeypatch):
    from cellcal.mocks import simulated_devices

    config = tracker_cell()
    db = str(tmp_path / "c.db")
    original = simulated_devices.SimulatedRobot.move_joints
    calls = {"n": 0}

    def faulty(self, q, speed):
        calls["n"] += 1
        if calls["n"] == 12:
            from cellcal.errors import DeviceError

            raise DeviceError("robot: protective stop")
        original(self, q, speed)

    monkeypatch.setattr(simulated_devices.SimulatedRobot, "move_joints", faulty)
    config = with_robot(config, driver="simulated")
    with pytest.raises(
        CampaignError, match=r"protective stop; campaign 1 is resumable: cellcal run --resume 1"
    ):
        start_campaign(config, db, config_path=None, mock=True)
    conn = sqlite3.connect(db)
    assert conn.execute(
        "SELECT kind, pose_idx FROM events WHERE kind = 'device-error'"
    ).fetchall() == [("device-error", 11)]
    last_t = conn.execute("SELECT MAX(t_end) FROM poses").fetchone()[0]
    conn.close()
    monkeypatch.setattr(simulated_devices.SimulatedRobot, "move_joints", original)
    out = resume_campaign(db, 1)
    assert out.summary is not None
    conn = sqlite3.connect(db)
    t = [r[0] for r in conn.execute("SELECT t_start FROM poses ORDER BY idx")]
    # The resumed simulated clock goes on from where the campaign stopped.
    assert t == sorted(t) and t[11] >= last_t

    # Fresh noise after the resume: the first resumed pose does not repeat the noise of
    # the campaign's first pose (a generator restarted from the seed would).
    def noise(idx):
        rows = conn.execute(
            "SELECT s.x, s.y, s.z FROM samples s JOIN poses p ON p.id = s.pose_id "
            "WHERE p.idx = ? AND s.sensor = 'tracker' ORDER BY s.id",
            (idx,),
        ).fetchall()
        a = np.array(rows)
        return a - a.mean(axis=0)

    assert not np.allclose(noise(11), noise(0))
    conn.close()


def test_ur10e_cell_through_ur_rtde(tmp_path):
    """The bundled UR variant: the robot through ur_rtde and the UR twin, the tracker
    through the line protocol, end to end in a real process."""
    config = Path(__file__).resolve().parents[2] / "config" / "mock-cell-ur10e.toml"
    res = _process(
        "run", "--mock", "--config", config, "--db", tmp_path / "ur.db", "--json", timeout=300
    )
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["n_calibration_poses"] == 80
    assert doc["rms_after_mm"] < doc["rms_before_mm"] / 10
    assert doc["calibration"]["unidentifiable"] == ["theta1", "d1", "theta6", "d6", "a6", "alpha6"]


def test_campaigns_run_on_devices_they_are_handed_and_leave_them_open(tmp_path):
    """A service holds its devices for its life: two campaigns on the same devices, which
    stay connected between them; every record of both reached the watcher."""
    from cellcal.campaign.devices import build_devices
    from cellcal.campaign.records import CampaignEnded, CampaignStarted, PoseStored
    from cellcal.clock import SimulatedClock

    config = tracker_cell()
    config = config.model_copy(
        update={
            "campaign": config.campaign.model_copy(
                update={"grid": [3, 3, 3], "validation_inside": 4, "validation_per_region": 1}
            )
        }
    )
    nominal = load_model(config.robot.model).model
    clock = SimulatedClock()
    devices = build_devices(config, nominal, clock, mock=True, seed=config.simulation.seed)
    seen = []
    try:
        outs = [
            start_campaign(
                config,
                str(tmp_path / "c.db"),
                config_path=None,
                mock=True,
                devices=devices,
                clock=clock,
                subscribers=[seen.append],
            )
            for _ in range(2)
        ]
        assert [o.campaign_id for o in outs] == [1, 2]
        assert all(o.summary is not None for o in outs)
        devices.robot.move_joints(np.radians(config.robot.home_deg), 0.25)  # still connected
    finally:
        devices.close()
    starts = [r for r in seen if isinstance(r, CampaignStarted)]
    ends = [r for r in seen if isinstance(r, CampaignEnded)]
    poses = [r for r in seen if isinstance(r, PoseStored)]
    assert [r.campaign_id for r in starts] == [1, 2] and [r.status for r in ends] == 2 * [
        "complete"
    ]
    assert len(poses) == 2 * len(outs[0].plan.poses) and ends[0].summary is outs[0].summary
    assert starts[0].config_digest == starts[1].config_digest
