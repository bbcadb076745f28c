"""Point CSV files: the contract's format and every way a file can be wrong."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.errors import FileFormatError, InputError
from cellcal.files.points import match_points, read_points


def write(tmp_path, text, name="p.csv", encoding="utf-8"):
    p = tmp_path / name
    p.write_text(text, encoding=encoding)
    return p


def test_reads_names_and_ignores_extra_columns(tmp_path):
    p = write(tmp_path, "\ufeffName, x ,y,z,comment\nA,1,2,3,first\n\nB, 4.5 ,-6e1,7,\n")
    pts = read_points(p)
    assert pts.names == ("A", "B")
    np.testing.assert_array_equal(pts.xyz, [[1, 2, 3], [4.5, -60, 7]])
    assert pts.sigma is None


def test_reads_optional_sigma_columns(tmp_path):
    pts = read_points(write(tmp_path, "name,x,y,z,sx,sy,sz\nA,1,2,3,0.01,0.02,0.03\n"))
    np.testing.assert_array_equal(pts.sigma, [[0.01, 0.02, 0.03]])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty file"),
        ("name,x,y\nA,1,2\n", "lacks column.*z"),
        ("x,y,z\n1,2,3\n", "lacks column.*name"),
        ("name,x,y,z\n", "no data rows"),
        ("name,x,y,z\nA,1,2,oops\n", r"p.csv:2: z is not a number: 'oops'"),
        ("name,x,y,z\nA,1,2,nan\n", "not finite"),
        ("name,x,y,z\nA,1,2,inf\n", "not finite"),
        ("name,x,y,z\nA,1,2\n", "3 fields"),
        ("name,x,y,z\n,1,2,3\n", "empty point name"),
        ("name,x,y,z\nA,1,2,3\nB,1,2,3\nA,4,5,6\n", "'A' already used on line 2"),
        ("name,x,x,y,z\nA,1,2,3,4\n", "appears twice"),
        ("name,x,y,z,sx,sy,sz\nA,1,2,3,0,1,1\n", "positive"),
    ],
)
def test_bad_files(tmp_path, text, match):
    with pytest.raises(FileFormatError, match=match):
        read_points(write(tmp_path, text))


def test_missing_file_and_directory_and_binary(tmp_path):
    with pytest.raises(FileFormatError, match="no such file"):
        read_points(tmp_path / "missing.csv")
    with pytest.raises(FileFormatError, match="directory"):
        read_points(tmp_path)
    b = tmp_path / "b.csv"
    b.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(FileFormatError, match="UTF-8"):
        read_points(b)


def test_match_by_name_with_warnings(tmp_path):
    a = read_points(write(tmp_path, "name,x,y,z\nA,1,0,0\nB,0,1,0\nC,0,0,1\nD,1,1,1\n", "a.csv"))
    b = read_points(write(tmp_path, "name,x,y,z\nE,9,9,9\nC,0,0,3\nA,1,0,2\nB,0,1,2\n", "b.csv"))
    m = match_points(a, b)
    assert m.names == ("A", "B", "C")
    np.testing.assert_array_equal(m.dst, [[1, 0, 2], [0, 1, 2], [0, 0, 3]])
    assert len(m.warnings) == 2
    assert "only in src" in m.warnings[0] and "D" in m.warnings[0]
    assert "only in dst" in m.warnings[1] and "E" in m.warnings[1]


def test_fewer_than_three_common_names(tmp_path):
    a = read_points(write(tmp_path, "name,x,y,z\nA,1,0,0\nB,0,1,0\nC,0,0,1\n", "a.csv"))
    b = read_points(write(tmp_path, "name,x,y,z\nA,1,0,0\nB,0,1,0\nX,0,0,1\n", "b.csv"))
    with pytest.raises(InputError, match="2 point name"):
        match_points(a, b)
