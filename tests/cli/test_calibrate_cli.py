"""``cellcal calibrate``, ``predict`` and ``models`` through the entry point."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cellcal.calib.identification import calibrate
from cellcal.cli import main
from cellcal.files.models import load_model
from tests.calib.simulated import well_spread


def run(capsys, *args):
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def write_measurements(path, q, m, sigma=None, names=True):
    head = (["name"] if names else []) + [f"q{i}" for i in range(1, 7)] + ["x", "y", "z"]
    if sigma is not None:
        head += ["sx", "sy", "sz"]
    rows = [",".join(head)]
    for k, (qi, mi) in enumerate(zip(q, m, strict=True)):
        cells = ([f"P{k + 1}"] if names else []) + [repr(math.degrees(v)) for v in qi]
        cells += [repr(float(v)) for v in mi]
        if sigma is not None:
            cells += [repr(float(v)) for v in sigma[k]]
        rows.append(",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture
def data_csv(tmp_path):
    d = well_spread("kuka-kr5-arc")
    return write_measurements(tmp_path / "meas.csv", d.q, d.m), d


def test_calibrate_json_contract_and_model_file(capsys, tmp_path, data_csv):
    path, d = data_csv
    out = tmp_path / "cal.toml"
    code, stdout, err = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path, "--out", out, "--json"
    )
    assert code == 0, err
    doc = json.loads(stdout)
    for key in (
        "n_points",
        "rms_before_mm",
        "rms_after_mm",
        "max_after_mm",
        "condition_number",
        "identified",
        "unidentifiable",
    ):
        assert key in doc
    assert doc["n_points"] == 80
    assert doc["rms_after_mm"] < 0.03 < doc["rms_before_mm"]
    assert "theta1" in doc["unidentifiable"] and "beta2" in doc["identified"]
    assert doc["validation"]["method"] == "k-fold k=5"
    assert doc["validation"]["after"]["rms_mm"] < doc["validation"]["before"]["rms_mm"] / 10
    # The file predicts what the fit predicts.
    res = calibrate(load_model("kuka-kr5-arc").model, d.q, d.m)
    joints = tmp_path / "joints.csv"
    joints.write_text(
        "q1,q2,q3,q4,q5,q6\n"
        + "\n".join(",".join(repr(math.degrees(v)) for v in q) for q in d.q_val[:5])
        + "\n"
    )
    code, stdout, _ = run(capsys, "predict", "--model", out, "--joints", joints)
    assert code == 0
    rows = [list(map(float, line.split(","))) for line in stdout.splitlines()[1:]]
    np.testing.assert_allclose(np.array(rows)[:, 6:], res.predict(d.q_val[:5]), atol=2e-6)


def test_human_report(capsys, data_csv):
    path, _ = data_csv
    code, out, _ = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path, "--folds", "3"
    )
    assert code == 0
    assert "validation (k-fold k=3" in out
    assert "left at nominal: theta1, d1, theta6, d6, a6, alpha6" in out
    assert "beta2" in out and "sensor frame" in out
    assert "0.200 mm with its registration vs 0.436 mm with another (2.18×" in out


def test_validate_file_and_no_folds(capsys, tmp_path, data_csv):
    path, d = data_csv
    val = write_measurements(tmp_path / "val.csv", d.q_val[:50], d.m_val_true[:50], names=False)
    code, out, _ = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path, "--validate", val, "--json"
    )
    assert code == 0
    assert json.loads(out)["validation"]["method"] == "file"
    code, out, _ = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path, "--folds", "0", "--json"
    )
    assert json.loads(out)["validation"] is None


def _one_line(code, out, err, match):
    assert code == 2, err
    assert out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert match in err


def test_user_errors_write_nothing(capsys, tmp_path, data_csv):
    path, d = data_csv
    out = tmp_path / "never.toml"
    q = d.q.copy()
    q[3, 2] = math.radians(170.0)
    outside = write_measurements(tmp_path / "outside.csv", q, d.m)
    few = write_measurements(tmp_path / "few.csv", d.q[:6], d.m[:6])
    nan = tmp_path / "nan.csv"
    nan.write_text(
        path.read_text().replace(path.read_text().splitlines()[5].split(",")[8], "nan", 1)
    )
    nocol = tmp_path / "nocol.csv"
    nocol.write_text("q1,q2,q3,q4,q5,q6,x,y\n1,2,3,4,5,6,7,8\n")
    cases = [
        (["--model", "kuka-kr5-arc", "--data", outside], "joint 3 reads 170.000°"),
        (["--model", "kuka-kr5-arc", "--data", few], "poses"),
        (["--model", "kuka-kr5-arc", "--data", nan], "not finite"),
        (["--model", "kuka-kr5-arc", "--data", nocol], "lacks column(s) z"),
        (["--model", "kuka-kr6", "--data", path], "not a built-in model"),
        (["--model", "kuka-kr5-arc", "--data", tmp_path / "missing.csv"], "no such file"),
        (["--model", "kuka-kr5-arc", "--data", path, "--folds", "1"], "--folds"),
        (["--model", "kuka-kr5-arc", "--data", path, "--robust", "magic"], "magic"),
    ]
    for args, match in cases:
        _one_line(*run(capsys, "calibrate", *args, "--out", out), match)
        assert not out.exists()
    directory = ["--model", "kuka-kr5-arc", "--data", path, "--folds", "0", "--out", tmp_path]
    _one_line(*run(capsys, "calibrate", *directory), "is a directory")


def test_models_and_predict_nominal(capsys, tmp_path):
    code, out, _ = run(capsys, "models", "--json")
    assert code == 0
    names = [m["name"] for m in json.loads(out)["models"]]
    assert names == ["kuka-kr5-arc", "ur10e", "ur5e"]
    code, out, _ = run(capsys, "models")
    assert "ur10e" in out and "2, 3" in out
    assert all(line == line.rstrip() for line in out.splitlines())  # no trailing spaces
    joints = tmp_path / "j.csv"
    joints.write_text("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n")
    code, out, _ = run(capsys, "predict", "--model", "kuka-kr5-arc", "--joints", joints)
    assert code == 0
    # All zeros: x = a1 + a2·cos(−90°)... the DH table gives (915, 0, 1120) for the flange.
    assert out.splitlines()[1].endswith("915.000000,0.000000,1120.000000")
    bad = tmp_path / "bad.csv"
    bad.write_text("q1,q2,q3,q4,q5,q6\n0,0,170,0,0,0\n")
    _one_line(*run(capsys, "predict", "--model", "kuka-kr5-arc", "--joints", bad), "outside")
    out_file = tmp_path / "p.csv"
    code, out, _ = run(capsys, "predict", "--model", "ur10e", "--joints", joints, "--out", out_file)
    assert code == 0 and out == "" and out_file.read_text().startswith("q1,")


def test_validation_from_another_set_up_says_to_re_register(tmp_path, capsys):
    from cellcal.calib.geometry import so3_exp

    d = well_spread("kuka-kr5-arc")
    data = write_measurements(tmp_path / "m.csv", d.q, d.m)
    R = so3_exp(np.array([0.3, 0.1, -0.2]))
    moved_xyz = d.m[:20] @ R.T + np.array([400.0, -200.0, 50.0])
    moved = write_measurements(tmp_path / "moved.csv", d.q[:20], moved_xyz)
    code, _, err = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data, "--validate", moved
    )
    assert code == 2 and "another set-up" in err and "--fix kinematics" in err
    model = tmp_path / "cal.toml"
    code, _, _ = run(capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data, "--out", model)
    assert code == 0
    code, out, err = run(
        capsys,
        "calibrate",
        "--model",
        model,
        "--fix",
        "kinematics",
        "--data",
        moved,
        "--folds",
        "0",
        "--json",
    )
    assert code == 0, err
    doc = json.loads(out)
    assert doc["identified"] == ["target_offset_x", "target_offset_y", "target_offset_z"]
    assert doc["rms_after_mm"] < 0.03


def test_a_weighted_fit_gives_plans_equal_weights_condition_number_too(capsys, tmp_path):
    """With sx,sy,sz the fit weighs each coordinate, which moves its condition number;
    the line and the JSON also give the one `cellcal plan` computes, every coordinate
    weighted alike: without sx,sy,sz the two are the same number."""
    d = well_spread("kuka-kr5-arc")
    sigma = np.tile([0.002, 0.002, 0.02], (len(d.q), 1))  # one axis ten times worse
    weighted = write_measurements(tmp_path / "w.csv", d.q, d.m, sigma=sigma)
    plain = write_measurements(tmp_path / "p.csv", d.q, d.m)
    docs = {}
    for name, path in (("weighted", weighted), ("plain", plain)):
        code, out, err = run(capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path)
        assert code == 0, err
        (line,) = [x for x in out.splitlines() if x.startswith("condition number")]
        code, out, err = run(
            capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path, "--json"
        )
        docs[name] = (line, json.loads(out))
    line, doc = docs["weighted"]
    equal = doc["condition_number_equal_weights"]
    assert abs(doc["condition_number"] / equal - 1) > 0.05  # the weights move it
    assert f"weighted by sx,sy,sz ({equal:.4g} with equal weights, `plan`'s measure)" in line
    line, doc = docs["plain"]
    assert doc["condition_number_equal_weights"] == pytest.approx(doc["condition_number"])
    assert "equal weights" not in line
    # the same poses weighted alike (each fit linearised at its own start): within 1 %
    assert equal == pytest.approx(doc["condition_number"], rel=0.01)
