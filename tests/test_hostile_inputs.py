"""Hostile input through the command line: every case is one line on stderr and exit 2
(never a traceback, a hang or a MemoryError), and the readers accept only what they
can use."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellcal.cli import main
from cellcal.errors import FileFormatError
from cellcal.files.measurements import read_measurements

DATA = "q1,q2,q3,q4,q5,q6,x,y,z\n" + "\n".join(
    f"{i},{-30 + i},{40 + i},{i},{-20 + i},{i},{800 + 10 * i},{5 * i},{900 - 3 * i}"
    for i in range(12)
)
CONFIG = Path(__file__).parents[1] / "config" / "mock-cell.toml"


def _one_line_exit_2(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as info:
        main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert info.value.code == 2, err
    assert len(err) == 1 and err[0].startswith("cellcal: error: "), err
    return err[0]


@pytest.fixture
def specials(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    loop = tmp_path / "loop"
    os.symlink(tmp_path / "loop2", loop)
    os.symlink(loop, tmp_path / "loop2")
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    return {
        "/dev/zero": ("/dev/zero", "not a regular file"),
        "fifo": (str(fifo), "not a regular file"),
        "symlink loop": (str(loop), "loop of symbolic links"),
        "deep nesting": (str(deep), "nested too deeply"),
    }


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", ["/dev/zero", "fifo", "symlink loop", "deep nesting"])
def test_special_files_as_config_model_and_csv(capsys, specials, case, tmp_path):
    path, expect = specials[case]
    good = tmp_path / "good.csv"
    good.write_text(DATA)
    assert expect in _one_line_exit_2(capsys, "run", "--config", path, "--mock")
    assert expect in _one_line_exit_2(capsys, "predict", "--model", path, "--joints", str(good))
    if case != "deep nesting":
        line = _one_line_exit_2(capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", path)
        assert expect in line
        assert expect in _one_line_exit_2(capsys, "register", "--src", path, "--dst", str(good))


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_unreadable_files(capsys, tmp_path):
    p = tmp_path / "secret.csv"
    p.write_text(DATA)
    p.chmod(0)
    assert "permission denied" in _one_line_exit_2(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", str(p)
    )


@pytest.mark.parametrize("value", ["1e9", "1e300", "inf", "nan", "-1"])
def test_time_scales_that_would_never_finish_or_overflow(capsys, tmp_path, value):
    db = tmp_path / "c.db"
    line = _one_line_exit_2(capsys, "run", "--mock", "--db", str(db), "--time-scale", value)
    assert "--time-scale" in line
    assert not db.exists()
    line = _one_line_exit_2(capsys, "mock", "tracker", "--time-scale", value)
    assert "--time-scale" in line


@pytest.mark.parametrize(
    ("edit", "expect"),
    [
        (
            ("cube_centre_mm = [750.0, 0.0, 1000.0]", "cube_centre_mm = [nan, 0.0, 1000.0]"),
            "finite",
        ),
        (("cube_edge_mm = 200.0", "cube_edge_mm = inf"), "finite"),
        (("cube_edge_mm = 200.0", "cube_edge_mm = 0.2"), "metres"),
        (("[simulation]", "[simulation]\njoint_speed_deg_s = inf"), "finite"),
        (("seed = 2018", "seed = -1"), "seed"),
        (("dwell_s = 7.0", "dwell_s = 1e300"), "dwell_s"),
    ],
)
def test_configs_with_absurd_numbers(capsys, tmp_path, edit, expect):
    text = CONFIG.read_text()
    assert edit[0] in text
    p = tmp_path / "cell.toml"
    p.write_text(text.replace(edit[0], edit[1], 1))
    line = _one_line_exit_2(
        capsys, "run", "--config", str(p), "--mock", "--db", str(tmp_path / "c.db")
    )
    assert expect in line
    assert not (tmp_path / "c.db").exists()


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        (DATA.replace("800,", "800,5,", 1), "a decimal comma"),
        (DATA.replace(",", ";"), "semicolon-delimited"),
        (DATA + '\n"1\n",2,3,4,5,6,7,8,9', "spans lines"),
        (DATA.replace("800,", "1e200,", 1), "out of range"),
        ("q1,q2\n", "header lacks"),
    ],
)
def test_measurement_csvs(capsys, tmp_path, text, expect):
    p = tmp_path / "m.csv"
    p.write_text(text)
    line = _one_line_exit_2(capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", str(p))
    assert expect in line
    assert re.search(r"m\.csv(:\d+)?: ", line)


def test_tracker_export_headers_with_units_are_read(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text(DATA.replace("x,y,z", "X [mm],Y [mm],Z (mm)", 1).replace("q1,", "Q1 [deg],", 1))
    m = read_measurements(p)
    assert m.xyz.shape == (12, 3) and m.q.shape == (12, 6)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.text(st.sampled_from('q1234567xyzsn,;."\n\r -e9inf[]'), max_size=300))
def test_any_text_is_a_measurement_file_or_one_clear_error(tmp_path, text):
    p = tmp_path / "fuzz.csv"
    p.write_text(text)
    try:
        read_measurements(p)
    except FileFormatError as exc:
        assert "\n" not in str(exc)
