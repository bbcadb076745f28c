"""Error terms through the entry point: ``calibrate --terms`` and its JSON, the
``time_s``/``temperature_c``/``payload_kg`` columns, the model file's [[term]] tables
read back by ``predict``, and refusals in one line."""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np

from cellcal.calib.error_terms import Conditions, Term
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import measure, random_cell, random_joints
from tests.cli.test_calibrate_cli import run

DRIFT = Term("drift", 0, ("x", "y", "z", "scale"), (0.02, -0.01, 0.03, 4e-6), variable="time_s")


def _drifting_csv(tmp_path, rows=240):
    """A simulated UR5e measured for four hours while its cell drifts."""
    nominal = load_model("ur5e").model
    rng = np.random.default_rng(11)
    cell = random_cell(nominal, rng)
    q = random_joints(nominal, rng, rows)
    time_s = np.sort(rng.uniform(0.0, 4 * 3600.0, rows))
    truth = replace(cell, model=cell.model.with_terms((DRIFT,)))
    m = measure(truth, q, rng, 0.02, Conditions(time_s=time_s))
    head = [f"q{i}" for i in range(1, 7)] + ["x", "y", "z", "time_s", "temperature_c"]
    lines = [",".join(head)]
    for qi, mi, t in zip(q, m, time_s, strict=True):
        cells = [repr(math.degrees(v)) for v in qi] + [repr(float(v)) for v in mi]
        lines.append(",".join([*cells, f"{t:.1f}", "21.5"]))
    path = tmp_path / "drifting.csv"
    path.write_text("\n".join(lines) + "\n")
    return path, q, cell


def _calibrate(capsys, path, *more):  # type: ignore[no-untyped-def]
    """``cellcal calibrate`` of the simulated UR5e's data, without k-fold validation."""
    return run(capsys, "calibrate", "--model", "ur5e", "--data", path, "--folds", "0", *more)


def test_calibrate_accepts_drift_and_predict_reads_time(capsys, tmp_path):
    path, q, cell = _drifting_csv(tmp_path)
    out = tmp_path / "cal.toml"
    code, stdout, err = _calibrate(capsys, path, "--out", out, "--json")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["terms"]["accepted"] == ["drift"]
    assert set(doc["terms"]["rejected"]) == {"gravity", "compliance", "harmonics", "ratio"}
    assert doc["blocked_cv_mm"]["final"] < doc["blocked_cv_mm"]["geometric"]
    model = tomllib.loads(out.read_text())
    (term,) = model["term"]
    assert term["name"] == "drift" and term["variable"] == "time_s"
    assert term["units"] == ["mm/h", "mm/h", "mm/h", "ppm/h"]
    assert abs(term["coefficients"][2] - 0.03) < 5 * term["sigma"][2]
    assert model["fit"]["terms"]["accepted"] == ["drift"]

    # predict: the same joints two hours later sit where the drift puts them
    joints = tmp_path / "joints.csv"
    rows = ["q1,q2,q3,q4,q5,q6,time_s"]
    rows += [",".join(f"{math.degrees(v):.9f}" for v in q[0]) + f",{t}" for t in (0, 7200)]
    joints.write_text("\n".join(rows) + "\n")
    code, stdout, err = run(capsys, "predict", "--model", out, "--joints", joints)
    assert code == 0, err
    xyz = np.array([[float(v) for v in line.split(",")[6:9]] for line in stdout.splitlines()[1:]])
    moved = cell.T_sensor_base[:3, :3].T @ (xyz[1] - xyz[0])  # into the base frame
    coefficients = term["coefficients"]
    assert np.allclose(moved, 2.0 * np.array(coefficients[:3]), atol=0.01)


def test_calibrate_text_says_each_terms_verdict(capsys, tmp_path):
    path, _, _ = _drifting_csv(tmp_path)
    code, stdout, err = _calibrate(capsys, path, "--terms", "drift")
    assert code == 0, err
    assert "error terms beyond geometry (list)" in stdout
    assert "drift: accepted — blocked cross-validation over later stretches" in stdout
    assert "drift with time_s: x " in stdout


def test_geometric_calibration_has_no_terms(capsys, tmp_path):
    path, _, _ = _drifting_csv(tmp_path, rows=80)
    code, stdout, err = _calibrate(capsys, path, "--json", "--terms", "geometric")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["terms"] is None and doc["error_terms"] == []


def test_refusals_are_one_line(capsys, tmp_path):
    path, _, _ = _drifting_csv(tmp_path, rows=30)
    code, _, err = run(capsys, "calibrate", "--model", "ur5e", "--data", path, "--terms", "wobble")
    assert code == 2 and "choose auto, geometric" in err and len(err.strip().splitlines()) == 1
    text = path.read_text().splitlines()
    text[3] = text[3].rsplit(",", 1)[0] + ",294.6"  # kelvin, not °C
    path.write_text("\n".join(text) + "\n")
    code, _, err = run(capsys, "calibrate", "--model", "ur5e", "--data", path)
    assert code == 2 and "temperature_c 294.6 is not °C" in err, err
    assert len(err.strip().splitlines()) == 1


def test_urdf_export_says_what_the_terms_it_leaves_out_are_worth(capsys, tmp_path):
    real = Path(__file__).parents[1] / "data" / "real" / "ur5"
    model = tmp_path / "ur5.toml"
    code, _, err = run(
        capsys,
        "calibrate",
        "--model",
        real / "model.toml",
        "--data",
        real / "measurements.csv",
        "--out",
        model,
        "--folds",
        "0",
    )
    assert code == 0, err
    code, stdout, err = run(
        capsys, "export", "urdf", "--model", model, "--out", tmp_path / "ur5.urdf", "--json"
    )
    assert code == 0, err
    assert "a URDF holds geometry only" in err and "harmonics (joints 1, 2" in err
    lost = json.loads(stdout)["terms_left_out"]
    assert lost["terms"] == ["harmonics"]
    assert 0.05 < lost["rms_mm"] < lost["max_mm"] < 5.0
