"""The campaign report: the bundled cell's campaign with the tracker and the camera rig,
its report folder written, the numbers the page shows recomputed from the database equal to
the analysis' stored summary, and the page opened in headless Chromium (Debian's
chromium + chromium-driver): no errors, every figure there, nothing loaded from
elsewhere; a full-page screenshot is kept and its path printed."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from cellcal import __version__
from cellcal.reports.data import METHODS, report_data
from cellcal.reports.folder import write_report
from cellcal.store.database import Store
from tests.browser import chromium, needs_chromium
from tests.bundled_campaign import bundled_database

ROOT = Path(__file__).parents[2]

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.browser, pytest.mark.timeout(600)]


@pytest.fixture(scope="module")
def campaign(request, tmp_path_factory):
    """The bundled cell's campaign, tracker and rig: README's when its test runs in this
    session, else run here (tests/bundled_campaign.py)."""
    folder = tmp_path_factory.mktemp("report")
    db, _ = bundled_database(request, folder)
    return folder, str(db), 1


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def test_the_reports_numbers_are_the_analysis_numbers(campaign):
    _, db, cid = campaign
    store = Store(db, readonly=True)
    try:
        facts = {"model": store.campaign(cid).model, "mock": True}
        d = report_data(store, cid, facts, methods=True)
    finally:
        store.close()
    s = d.summary
    assert s is not None and d.validation is not None
    assert _rms(d.validation.before) == pytest.approx(s["rms_before_mm"], rel=1e-9)
    assert _rms(d.validation.after) == pytest.approx(s["rms_after_mm"], rel=1e-6)
    regs = {r["sensor"]: r for r in s["registrations"]}
    assert sorted(regs) == ["rig", "tracker"]
    for r in d.residuals:
        assert _rms(r.nominal) == pytest.approx(regs[r.sensor]["rms_nominal_mm"], rel=1e-9)
        assert _rms(r.calibrated) == pytest.approx(regs[r.sensor]["rms_calibrated_mm"], rel=1e-6)
    (rig,) = d.agreements
    assert rig.sensor == "rig"
    stored = {a["sensor"]: a for a in s["agreements"]}["rig"]
    assert len(rig.idx) == stored["n"]
    assert float(np.sqrt(np.mean(rig.distance_mm**2))) == pytest.approx(stored["rms_mm"], rel=1e-6)
    cond = d.singular_values[0] / d.singular_values[-1]
    assert cond == pytest.approx(s["calibration"]["condition_number"], rel=1e-3)
    # the plan's figure (equal weights) is there too, and lower: the tracker's σ differs
    # by axis
    equal = s["calibration"]["condition_number_equal_weights"]
    assert 1.0 < equal < s["calibration"]["condition_number"]
    # the headline's range: the measured RMS is one draw of it
    spread = s["rms_after_spread"]
    assert spread["low_mm"] < spread["median_mm"] < spread["high_mm"] < spread["alarm_mm"]
    assert spread["measured_mm"] == s["rms_after_mm"]
    assert spread["measured_mm"] < spread["alarm_mm"]
    assert s["cellcal_version"] == __version__
    by = {m.method: m for m in d.methods}
    assert tuple(by) == METHODS
    # Least squares methods agree; three points and the paper's lines do worse.
    assert by["quaternion"].validation_rms_mm == pytest.approx(
        by["svd"].validation_rms_mm, rel=1e-6
    )
    # least squares fits the registration's points best by construction; at held-out
    # poses three points usually do worse, but one draw of the noise may favour them
    assert by["three-point"].fit_rms_mm > by["svd"].fit_rms_mm
    kinds = [k for _, k, _, _ in d.events]
    assert "device" in kinds  # the tracker said who it is


def test_the_report_names_how_the_poses_were_chosen():
    from cellcal.reports.folder import plan_text

    optimal = '{"campaign": {"optimal_poses": 24, "optimal_criterion": "I", "grid": [4, 4, 5]}}'
    assert plan_text(optimal) == "24 I-optimal calibration poses of the cube's candidates"
    box = '{"campaign": {"optimal_poses": 30, "region": "workspace"}}'
    assert (
        plan_text(box)
        == "30 D-optimal calibration poses of candidates drawn over the workspace box"
    )
    assert plan_text('{"campaign": {"grid": [4, 4, 5]}}') == "the cube's grid, 4 × 4 × 5 points"
    assert plan_text("{}") == plan_text("not json") == "the cube's grid"


@needs_chromium
def test_the_report_page_renders_in_chromium(campaign, capsys):

    folder, db, cid = campaign
    store = Store(db, readonly=True)
    try:
        out = write_report(store, cid, folder / "out", methods=True)
        summary = store.latest_report(cid)
    finally:
        store.close()
    assert out.analysed and summary is not None
    page = Path(out.folder) / "index.html"
    text = page.read_text()
    # Self-contained: no script, nothing fetched.
    assert "<script" not in text
    assert not re.search(r'(src|href)="(?!#|data:)', text)

    browser = chromium(1280, 1200)
    from selenium.webdriver.common.by import By

    shot = folder / "report-page.png"
    try:
        browser.set_page_load_timeout(60)
        browser.get(page.as_uri())
        figures = {
            f.get_attribute("id"): f for f in browser.find_elements(By.CSS_SELECTOR, "figure")
        }
        expected = {
            "fig-validation",
            "fig-regions",
            "fig-registration-tracker",
            "fig-registration-rig",
            "fig-agreement-rig",
            "fig-singular-values",
            "fig-residuals-3d",
            "fig-methods",
        }
        assert set(figures) == expected
        for ident, fig in figures.items():
            svg = fig.find_element(By.TAG_NAME, "svg")
            assert svg.size["width"] > 200 and svg.size["height"] > 100, ident
            assert fig.find_element(By.TAG_NAME, "figcaption").text
        headline = browser.find_element(By.ID, "headline").text
        assert f"RMS {summary['rms_before_mm']:.4f} mm before" in headline
        assert f"{summary['rms_after_mm']:.4f} mm after" in headline
        spread = summary["rms_after_spread"]
        assert f"would give {spread['low_mm']:.4f}–{spread['high_mm']:.4f} mm" in headline
        body = browser.find_element(By.TAG_NAME, "body").text
        assert "0.200" in body and "Table 3" in body  # beside the paper's figures
        assert "mock mode" in body  # and says what a simulated campaign's numbers mean
        assert "cellcal mock-tracker, serial SIM-0001" in body
        assert "the cube's grid, 4 × 4 × 5 points" in body  # how the poses were chosen
        assert f"report by {__version__}; campaign acquired by {__version__}" in body
        errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
        height = browser.execute_script("return document.body.scrollHeight")
        browser.set_window_size(1280, min(int(height) + 100, 16000))
        browser.save_screenshot(str(shot))
    finally:
        browser.quit()
    kept = ROOT / ".pytest_cache" / "report-page"
    kept.mkdir(parents=True, exist_ok=True)
    shutil.copy(shot, kept / shot.name)
    with capsys.disabled():
        print(f"\n  report page screenshot: {kept / shot.name}")
