"""The ISO 9283 test in mock mode: a campaign calibrates the simulated robot; the test
then moves it through the standard's five points with the nominal model's joints and
with the calibrated model's, through the real drivers, and stores every sample."""

from __future__ import annotations

import csv
import html
import json
import re
import sqlite3

import numpy as np
import pytest

from cellcal.calib.iso9283 import iso_points
from cellcal.files.measurements import read_measurements
from tests.conftest import TRACKER_CELL
from tests.e2e.calibrated import calibrated_campaign, cli

pytestmark = [pytest.mark.twin, pytest.mark.timeout(300)]


CYCLES = 6


@pytest.fixture(scope="module")
def iso_test(tmp_path_factory):
    """One calibrated campaign (the shared fixture) and one ISO 9283 test after it, for
    every test of this module: the configuration, the campaign's outcome, the test's
    JSON output, its database and its folder."""
    tmp_path = tmp_path_factory.mktemp("iso9283")
    config, _, outcome, model_path = calibrated_campaign(tmp_path)
    iso_db = str(tmp_path / "iso.db")
    run = cli(
        "iso9283",
        "--mock",
        "--config",
        str(TRACKER_CELL),
        "--model",
        str(model_path),
        "--db",
        iso_db,
        "--cycles",
        str(CYCLES),
        "--json",
    )
    assert run.returncode == 0, run.stderr
    said = run.stderr.splitlines()  # its progress on stderr, in the test's words
    assert said[0].endswith(": planning the poses and starting the devices' twins…"), said
    assert f"acquiring {2 * 5 * CYCLES} of {2 * 5 * CYCLES} poses" in said
    assert said[-1] == "every visit stored: computing AP and RP, before and after…", said
    return config, outcome, json.loads(run.stdout), iso_db, tmp_path


def test_accuracy_improves_repeatability_stays_and_every_sample_is_stored(iso_test):
    config, outcome, result, iso_db, _ = iso_test
    cycles = CYCLES
    out = result["iso9283"]
    before, after = out["iso-before"]["points"], out["iso-after"]["points"]
    points = iso_points(np.array(config.campaign.cube_centre_mm), config.campaign.cube_edge_mm)
    for stage in (before, after):
        assert [p["point"] for p in stage] == ["P1", "P2", "P3", "P4", "P5"]
        np.testing.assert_allclose([p["commanded_mm"] for p in stage], points)
        assert all(p["n"] == cycles for p in stage)
    ap_b = np.array([p["ap_mm"] for p in before])
    ap_a = np.array([p["ap_mm"] for p in after])
    rp_a = np.array([p["rp_mm"] for p in after])
    print(f"AP before {ap_b.round(4)}, after {ap_a.round(4)}; RP after {rp_a.round(4)} mm")
    # The nominal model misses by the injected errors; the calibrated one by about the
    # validation error inside the cube.
    assert ap_b.min() > 0.2
    assert ap_a.max() < 0.05 * ap_b.min()
    assert ap_a.max() < 3 * outcome.summary.inside.after.rms
    # The simulated robot returns exactly: RP is the tracker's noise on 20-sample means.
    assert rp_a.max() < 0.05
    conn = sqlite3.connect(iso_db)
    try:
        n_poses, status = conn.execute("SELECT n_poses, status FROM campaigns").fetchone()
        assert (n_poses, status) == (2 * 5 * cycles, "complete")
        samples = conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        assert samples == n_poses * config.campaign.samples_per_pose
        roles = dict(conn.execute("SELECT role, COUNT(*) FROM poses GROUP BY role").fetchall())
        assert roles == {"iso-before": 5 * cycles, "iso-after": 5 * cycles}
    finally:
        conn.close()


def _cells(page: str, ident: str) -> list[list[str]]:
    """The rows of the page's table ``ident``, as the text of their cells."""
    table = re.search(rf'<table id="{ident}">(.*?)</table>', page, re.S)
    assert table, ident
    return [
        [html.unescape(c) for c in re.findall(r"<t[dh][^>]*>(.*?)</t[dh]>", row)]
        for row in re.findall(r"<tr>(.*?)</tr>", table.group(1))
    ]


def test_the_report_is_the_iso_tests_with_its_numbers_and_its_samples(iso_test):
    """The report names the test (not a calibration on the cube's grid), shows the
    commanded points, barycentres and AP components equal to the stored summary, and
    its CSV holds every visit, readable by ``cellcal calibrate``."""
    _, _, result, iso_db, tmp_path = iso_test
    out = tmp_path / "iso-report"
    run = cli("report", "--db", iso_db, "--out", str(out), "--json")
    assert run.returncode == 0, run.stderr
    files = json.loads(run.stdout)["files"]
    assert "measurements-tracker.csv" in files and "validation-tracker.csv" not in files
    summary = json.loads((out / "summary.json").read_text())
    iso = summary["summary"]["iso9283"]
    assert iso == result["iso9283"]
    model = summary["summary"]["calibrated_model"]
    assert model.endswith("model.toml") and summary["summary"]["cycles"] == CYCLES
    plan = summary["plan"]
    assert plan.startswith("ISO 9283 AP/RP test: the standard's five points")
    assert f"{CYCLES} cycles" in plan and "kuka-kr5-arc" in plan and model in plan
    assert "cube" not in plan

    page = (out / "index.html").read_text()
    text = html.unescape(re.sub(r"<[^>]+>", " ", page))
    assert "<title>cellcal ISO 9283 test (campaign 1)</title>" in page
    assert "cube's grid" not in text and "calibration poses" not in text
    assert "4 × 4 × 5" not in text and "4×4×5" not in text
    (poses,) = [r for r in _cells(page, "campaign") if r[0] == "test poses"]
    assert poses[1] == plan and "cube" not in poses[1]
    points = iso["iso-before"]["points"]
    commanded = _cells(page, "iso-commanded")
    assert commanded[0] == ["point", "x", "y", "z"]
    assert commanded[1:] == [[p["point"], *(f"{v:.4f}" for v in p["commanded_mm"])] for p in points]
    summary_rows = _cells(page, "iso-summary")
    assert summary_rows[0] == [
        "point",
        "AP iso-before",
        "AP iso-after",
        "RP iso-before",
        "RP iso-after",
    ]
    for stage in ("iso-before", "iso-after"):
        rows = _cells(page, stage)
        assert rows[0][:8] == ["point", "x̄", "ȳ", "z̄", "APx", "APy", "APz", "AP"]
        for row, p in zip(rows[1:], iso[stage]["points"], strict=True):
            numbers = [*p["barycentre_mm"], *p["ap_xyz_mm"], p["ap_mm"], p["l_mean_mm"]]
            numbers += [p["s_l_mm"], p["rp_mm"]]
            assert row == [p["point"], *(f"{v:.4f}" for v in numbers), str(CYCLES)]
    for row, b, a in zip(summary_rows[1:], points, iso["iso-after"]["points"], strict=True):
        assert row == [
            b["point"],
            *(f"{v:.4f}" for v in (b["ap_mm"], a["ap_mm"], b["rp_mm"], a["rp_mm"])),
        ]

    # Every visit, readable by calibrate's reader and by any CSV reader.
    csv_path = out / "measurements-tracker.csv"
    data = read_measurements(csv_path, 6)
    assert len(data.q) == 2 * 5 * CYCLES and data.sigma is not None
    with csv_path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    for stage in ("iso-before", "iso-after"):
        for p in iso[stage]["points"]:
            visits = [r for r in rows if r["stage"] == stage and r["point"] == p["point"]]
            assert sorted(int(r["cycle"]) for r in visits) == list(range(1, CYCLES + 1))
            for r in visits:
                c = [float(r[f"commanded_{a}"]) for a in "xyz"]
                np.testing.assert_allclose(c, p["commanded_mm"], rtol=0, atol=1e-9)
            attained = np.array([[float(r[f"attained_{a}"]) for a in "xyz"] for r in visits])
            np.testing.assert_allclose(attained.mean(axis=0), p["barycentre_mm"], atol=1e-9)
            ap = attained.mean(axis=0) - np.array(p["commanded_mm"])
            np.testing.assert_allclose(ap, p["ap_xyz_mm"], atol=1e-9)


def test_a_nominal_model_and_too_few_cycles_are_refused(tmp_path):
    run = cli("iso9283", "--mock", "--model", "kuka-kr5-arc", "--db", str(tmp_path / "x.db"))
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "calibrated model" in run.stderr
    run = cli("iso9283", "--mock", "--model", "kuka-kr5-arc", "--cycles", "1")
    assert run.returncode == 2
