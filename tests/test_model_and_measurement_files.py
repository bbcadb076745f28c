"""Model files (built-in, TOML, calibrated) and measurement / joint CSV files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.calib.identification import calibrate
from cellcal.errors import FileFormatError, InputError
from cellcal.files.measurements import format_positions, read_joints, read_measurements
from cellcal.files.models import load_model, write_atomically, write_calibrated
from tests.calib.simulated import well_spread


def test_model_file_errors(tmp_path):
    with pytest.raises(FileFormatError, match="not a built-in model"):
        load_model(str(tmp_path / "nope.toml"))
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed\n")
    with pytest.raises(FileFormatError, match="not valid TOML"):
        load_model(str(bad))
    typo = tmp_path / "typo.toml"
    typo.write_text(
        'name = "x"\nconvention = "dh"\n[[joint]]\na = 1\nalpha = 0\nd = 0\ntheta = 0\nlenght = 3\n'
    )
    with pytest.raises(InputError, match="unknown key 'lenght'"):
        load_model(str(typo))


def test_calibrated_model_round_trip(tmp_path):
    d = well_spread("ur5e", seed=4, n=40)
    nominal = load_model("ur5e").model
    res = calibrate(nominal, d.q, d.m)
    out = tmp_path / "cal.toml"
    write_calibrated(out, res, None, "data.csv")
    loaded = load_model(str(out))
    assert loaded.calibrated
    # Angles are written in degrees rounded at 1e-12°: equal to ~1e-14 rad.
    for a, b in zip(loaded.model.joints, res.calibrated.joints, strict=True):
        np.testing.assert_allclose(
            [a.a, a.alpha, a.d, a.theta, a.beta], [b.a, b.alpha, b.d, b.theta, b.beta], atol=1e-13
        )
    assert loaded.model.parallel == res.calibrated.parallel
    np.testing.assert_allclose(loaded.target_offset, res.target_offset)
    np.testing.assert_allclose(loaded.T_sensor_base, res.T_sensor_base)
    text = out.read_text()
    assert 'format = "cellcal-calibrated-model"' in text
    assert "[nominal]" in text and "[[parameter]]" in text and "[fit]" in text
    # A file written by an earlier version names the sensor frame's table [instrument].
    out.write_text(text.replace("[sensor]", "[instrument]"))
    np.testing.assert_allclose(load_model(str(out)).T_sensor_base, res.T_sensor_base)
    # A calibrated file whose sensor block is damaged is refused.
    out.write_text(text.replace("[sensor]", "[sensorx]"))
    with pytest.raises(FileFormatError, match="incomplete"):
        load_model(str(out))


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")
    write_atomically(target, "new")
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]
    with pytest.raises(FileFormatError, match="does not exist"):
        write_atomically(tmp_path / "missing" / "f.txt", "x")


def _write(tmp_path, text, name="m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_read_measurements(tmp_path):
    p = _write(
        tmp_path,
        "name,q1,q2,q3,q4,q5,q6,x,y,z,sx,sy,sz,comment\n"
        "A,10,20,30,40,50,60,1,2,3,0.01,0.01,0.02,ok\n"
        "B,0,0,0,0,0,-90,4,5,6,0.01,0.01,0.02,\n",
    )
    m = read_measurements(p)
    assert m.names == ("A", "B")
    np.testing.assert_allclose(m.q[0], np.radians([10, 20, 30, 40, 50, 60]))
    np.testing.assert_allclose(m.xyz[1], [4, 5, 6])
    np.testing.assert_allclose(m.sigma[0], [0.01, 0.01, 0.02])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("q1,q2,q3,q4,q5,x,y,z\n1,2,3,4,5,1,2,3\n", "lacks column.*q6"),
        ("q1,q2,q3,q4,q5,q6,x,y\n1,2,3,4,5,6,1,2\n", "lacks column.*z"),
        ("q1,q2,q3,q4,q5,q6,x,y,z\n1,2,3,4,5,six,1,2,3\n", r"m.csv:2: q6 is not a number"),
        ("q1,q2,q3,q4,q5,q6,x,y,z\n1,2,3,4,5,6,1,NaN,3\n", "y is not finite"),
        ("q1,q2,q3,q4,q5,q6,q7,x,y,z\n1,2,3,4,5,6,7,1,2,3\n", "q7 but the robot has 6"),
        ("q1,q2,q3,q4,q5,q6,x,y,z,sx\n1,2,3,4,5,6,1,2,3,0.1\n", "all of sx, sy, sz"),
        ("q1,q2,q3,q4,q5,q6,x,y,z,sx,sy,sz\n1,2,3,4,5,6,1,2,3,0,1,1\n", "must be positive"),
        ("q1,q2,q3,q4,q5,q6,x,y,z\n", "no data rows"),
    ],
)
def test_bad_measurement_files(tmp_path, text, match):
    with pytest.raises(FileFormatError, match=match):
        read_measurements(_write(tmp_path, text))


def test_joints_and_positions_format(tmp_path):
    q = read_joints(_write(tmp_path, "q1,q2,q3,q4,q5,q6\n0,-90,90,0,45,180\n"))
    np.testing.assert_allclose(q, [np.radians([0, -90, 90, 0, 45, 180])])
    text = format_positions(q, np.array([[1.0, -1e-12, 2.5]]))
    assert text.splitlines() == [
        "q1,q2,q3,q4,q5,q6,x,y,z",
        "0.000000,-90.000000,90.000000,0.000000,45.000000,180.000000,1.000000,0.000000,2.500000",
    ]
    assert math.isclose(float(text.splitlines()[1].split(",")[1]), -90.0)
