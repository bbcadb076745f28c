"""``cellcal register`` through the real entry point: output contract and user errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cellcal.calib.registration import METHODS
from cellcal.cli import main
from tests.conftest import TABLE4_DST, TABLE4_SRC, rigid_problem


def run(capsys, *args):
    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def write_points(path, names, xyz, sigma=None):
    head = "name,x,y,z" + (",sx,sy,sz" if sigma is not None else "")
    rows = [head]
    for i, (n, p) in enumerate(zip(names, xyz, strict=True)):
        extra = "" if sigma is None else "," + ",".join(repr(float(v)) for v in sigma[i])
        rows.append(f"{n},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}{extra}")
    path.write_text("\n".join(rows) + "\n")
    return str(path)


def test_json_contract_on_table4(capsys):
    code, out, err = run(
        capsys, "register", "--src", str(TABLE4_SRC), "--dst", str(TABLE4_DST), "--json"
    )
    assert code == 0 and err == ""
    doc = json.loads(out)
    assert doc["method"] == "svd"
    assert np.array(doc["T"]).shape == (4, 4)
    assert doc["names"] == ["P1", "P2", "P3", "P4", "P5"]
    np.testing.assert_allclose(
        doc["residuals_mm"], [0.0138, 0.0168, 0.0231, 0.0229, 0.0316], atol=5e-5
    )
    assert doc["rms_mm"] == pytest.approx(0.0225, abs=5e-5)
    assert doc["max_mm"] == pytest.approx(0.0316, abs=5e-5)
    assert doc["loo_rms_mm"] > doc["rms_mm"]
    assert len(doc["translation_std_mm"]) == 3


@pytest.mark.parametrize("method", METHODS)
def test_every_method_runs_and_prints_a_report(capsys, method):
    code, out, _ = run(
        capsys, "register", "--src", str(TABLE4_SRC), "--dst", str(TABLE4_DST), "--method", method
    )
    assert code == 0
    assert f"method {method}" in out
    assert "RMS 0.02" in out


def test_line_method_with_named_lines(capsys):
    code, out, _ = run(
        capsys,
        "register",
        "--src",
        str(TABLE4_SRC),
        "--dst",
        str(TABLE4_DST),
        "--method",
        "line",
        "--line-a",
        "P1,P2",
        "--line-b",
        "P2,P3",
        "--json",
    )
    doc = json.loads(out)
    assert code == 0
    assert doc["support_points"] == [["P1", "P2"], ["P2", "P3"]]
    assert doc["rms_mm"] == pytest.approx(0.025, abs=0.001)


def test_names_matched_across_files_in_any_order(tmp_path, capsys):
    P, Q, R, _t = rigid_problem(1, n=6)
    names = [f"T{i}" for i in range(6)]
    src = write_points(tmp_path / "s.csv", names, P)
    order = [3, 0, 5, 1, 4]  # T2 missing in dst; an extra point X in dst
    dst = write_points(
        tmp_path / "d.csv", [names[i] for i in order] + ["X"], np.vstack([Q[order], [[0, 0, 0]]])
    )
    code, out, err = run(capsys, "register", "--src", src, "--dst", dst, "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["names"] == ["T0", "T1", "T3", "T4", "T5"]
    np.testing.assert_allclose(np.array(doc["T"])[:3, :3], R, atol=1e-9)
    assert "T2" in err and "X" in err and err.count("warning") == 2


def test_weighted_uses_sigma_columns(tmp_path, capsys):
    P, Q, _, _ = rigid_problem(2, n=8, noise=0.05)
    names = [f"p{i}" for i in range(8)]
    sig = np.full((8, 3), 0.01)
    sig[0] = 1.0  # a poor point barely counts
    src = write_points(tmp_path / "s.csv", names, P)
    dst = write_points(tmp_path / "d.csv", names, Q, sigma=sig)
    _, plain, _ = run(capsys, "register", "--src", src, "--dst", dst, "--json")
    code, weighted, _ = run(capsys, "register", "--src", src, "--dst", dst, "--json", "--weighted")
    assert code == 0
    assert json.loads(plain)["T"] != json.loads(weighted)["T"]


def test_robust_ransac_flags_outlier(tmp_path, capsys):
    P, Q, _, _ = rigid_problem(3, n=12, noise=0.01)
    Q[5] += 4.0
    names = [f"p{i}" for i in range(12)]
    src = write_points(tmp_path / "s.csv", names, P)
    dst = write_points(tmp_path / "d.csv", names, Q)
    code, out, _ = run(capsys, "register", "--src", src, "--dst", dst, "--robust", "ransac")
    assert code == 0
    assert [line.split()[0] for line in out.splitlines() if "outlier" in line] == ["p5"]


def _one_line_error(code, out, err, match):
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("cellcal: error:")
    assert match in lines[0]


def test_user_errors_are_one_line_exit_2(tmp_path, capsys):
    P, Q, _, _ = rigid_problem(4, n=6)
    names = [f"p{i}" for i in range(6)]
    good = write_points(tmp_path / "good.csv", names, P)
    mirrored = write_points(tmp_path / "m.csv", names, Q * [-1, 1, 1])
    line = write_points(tmp_path / "l.csv", names, np.outer(np.arange(6.0), [1, 2, 3]))
    two = write_points(tmp_path / "two.csv", names[:2], Q[:2])
    nan = tmp_path / "nan.csv"
    nan.write_text("name,x,y,z\np0,1,2,nan\n")
    cases = [
        (["--src", "missing.csv", "--dst", good], "no such file"),
        (["--src", good, "--dst", str(nan)], "not finite"),
        (["--src", good, "--dst", two], "2 point name(s) in common"),
        (["--src", good, "--dst", mirrored], "mirrored"),
        (["--src", line, "--dst", good], "collinear"),
        (["--src", good, "--dst", good, "--method", "magic"], "magic"),
        (["--src", good], "--dst"),
        (["--src", good, "--dst", good, "--line-a", "p0,p1"], "both --line-a and --line-b"),
        (
            [
                "--src",
                good,
                "--dst",
                good,
                "--method",
                "line",
                "--line-a",
                "p0,zz",
                "--line-b",
                "p1,p2",
            ],
            "zz",
        ),
        (["--src", good, "--dst", good, "--weighted"], "sx,sy,sz"),
        (["--src", good, "--dst", good, "--method", "line", "--scale"], "least-squares"),
        (["--src", good, "--dst", good, "--ransac-threshold", "1"], "--robust ransac"),
    ]
    for args, match in cases:
        _one_line_error(*run(capsys, "register", *args), match)


def test_real_process_exit_codes(tmp_path):
    """The installed entry point, as a script sees it."""
    ok = subprocess.run(
        [
            sys.executable,
            "-m",
            "cellcal",
            "register",
            "--src",
            str(TABLE4_SRC),
            "--dst",
            str(TABLE4_DST),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["method"] == "svd"
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "cellcal",
            "register",
            "--src",
            str(tmp_path / "x.csv"),
            "--dst",
            str(TABLE4_DST),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr


def test_version_and_help(capsys):
    code, out, _ = run(capsys, "--version")
    assert code == 0 and "cellcal, version" in out
    code, out, _ = run(capsys, "--help")
    assert code == 0 and "register" in out
    code, out, _ = run(capsys, "register", "--help")
    assert code == 0 and "--method" in out


def test_an_error_is_the_only_line_even_when_names_differ(tmp_path, capsys):
    P, Q, _, _ = rigid_problem(5, n=6)
    src = write_points(
        tmp_path / "s.csv", [f"p{i}" for i in range(6)] + ["ONLYSRC"], np.vstack([P, [[0, 0, 0]]])
    )
    dst = write_points(tmp_path / "d.csv", [f"p{i}" for i in range(6)], Q)
    for args, match in [
        (["--method", "line", "--line-a", "p0"], "both --line-a and --line-b"),
        (["--method", "three-point", "--points", "p0,p1"], "three different point names"),
        (["--scale", "--method", "three-point"], "least-squares"),
    ]:
        _one_line_error(*run(capsys, "register", "--src", src, "--dst", dst, *args), match)
    code, _, err = run(capsys, "register", "--src", src, "--dst", dst)
    assert code == 0 and "ONLYSRC" in err
