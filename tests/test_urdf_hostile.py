"""Hostile URDF files (issue 29, item 6): each is one line on stderr naming the file and
exit 2 — never a traceback, a hang or gigabytes of memory. The reader bounds the
joint and link count before Pinocchio sees the file, refuses DTDs and entities (billion
laughs, external entities) as defusedxml does, and turns whatever Pinocchio raises into
one line."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from tests.inprocess import cellcal

JOINTS = "q1,q2,q3,q4,q5,q6\n0,-30,40,0,-20,0\n"


def _joint(i: int, parent: str, child: str, kind: str = "revolute", **kw: str) -> str:
    origin = kw.get("origin", 'xyz="0 0 0.1" rpy="0 0 0"')
    axis = kw.get("axis", "0 0 1")
    limit = kw.get("limit", 'lower="-3" upper="3" effort="0" velocity="0"')
    extra = kw.get("extra", "")
    return (
        f'<joint name="{kw.get("name", f"j{i}")}" type="{kind}"><origin {origin}/>'
        f'<parent link="{parent}"/><child link="{child}"/><axis xyz="{axis}"/>'
        f"<limit {limit}/>{extra}</joint>"
    )


def chain(n: int = 6, *, links: list[str] | None = None, joints: list[str] | None = None) -> str:
    """A serial chain base_link → l1 … ln, revolute joints 0.1 m apart along z (turned
    about alternating axes), or the links and joints given."""
    if links is None:
        links = ["base_link", *(f"l{i}" for i in range(1, n + 1))]
    if joints is None:
        joints = [
            _joint(i, links[i - 1], links[i], axis="0 0 1" if i % 2 else "0 1 0")
            for i in range(1, n + 1)
        ]
    body = "".join(f'<link name="{name}"/>' for name in links) + "".join(joints)
    return f'<?xml version="1.0"?><robot name="hostile">{body}</robot>'


def _with(i: int, **kw: str) -> str:
    """The 6-joint chain with joint ``i`` (1-based) replaced."""
    links = ["base_link", *(f"l{k}" for k in range(1, 7))]
    joints = [
        _joint(k, links[k - 1], links[k], axis="0 0 1" if k % 2 else "0 1 0") for k in range(1, 7)
    ]
    kind = kw.pop("kind", "revolute")
    joints[i - 1] = _joint(i, links[i - 1], links[i], kind, **kw)
    return chain(links=links, joints=joints)


_NESTED = zip("abcdefgh", "bcdefghi", strict=True)
LAUGHS = (
    '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa">'
    + "".join(f'<!ENTITY {c} "{("&" + p + ";") * 10}">' for p, c in _NESTED)
    + ']><robot name="&i;"><link name="base_link"/></robot>'
)
LINKS6 = ["base_link", *(f"l{k}" for k in range(1, 7))]

CASES: dict[str, str | bytes] = {
    "empty file": "",
    "whitespace only": "   \n\t\n",
    "not XML": "this is not a robot\n",
    "truncated XML": chain()[:-30],
    "NUL bytes": "<robot name='x'>\x00</robot>",
    "not UTF-8": b"<robot name='\xff\xfe'></robot>",
    "root is not robot": '<?xml version="1.0"?><sdf version="1.6"/>',
    "empty robot": '<robot name="r"/>',
    "billion laughs": LAUGHS,
    "external entity": (
        '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
        '<robot name="&x;"><link name="base_link"/></robot>'
    ),
    "DOCTYPE alone": '<?xml version="1.0"?><!DOCTYPE robot><robot name="r"/>',
    "parameter entity": (
        '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY % p "x">]><robot name="r"/>'
    ),
    "missing parent link": chain(
        links=LINKS6[1:],
        joints=[_joint(k, LINKS6[k - 1], LINKS6[k]) for k in range(1, 7)],
    ),
    "missing child link": chain(
        links=LINKS6[:-1],
        joints=[_joint(k, LINKS6[k - 1], LINKS6[k]) for k in range(1, 7)],
    ),
    "loop": chain(
        links=["a", "b", "c"],
        joints=[_joint(1, "a", "b"), _joint(2, "b", "c"), _joint(3, "c", "a")],
    ),
    "two roots": chain(
        links=["a", "b", "c", "d"], joints=[_joint(1, "a", "b"), _joint(2, "c", "d")]
    ),
    "joint to itself": chain(links=["a"], joints=[_joint(1, "a", "a")]),
    "unknown joint type": _with(3, kind="banana"),
    "no joint type": _with(2).replace('type="revolute"', "", 1),
    "joint without parent": _with(4).replace('<parent link="l3"/>', ""),
    "NaN origin": _with(2, origin='xyz="nan 0 0.1" rpy="0 0 0"'),
    "inf origin": _with(2, origin='xyz="0 inf 0.1" rpy="0 0 0"'),
    "huge origin": _with(5, origin='xyz="1e308 1e308 1e308" rpy="0 0 0"'),
    "NaN rpy": _with(3, origin='xyz="0 0 0.1" rpy="nan 0 0"'),
    "origin of two numbers": _with(3, origin='xyz="0 0.1" rpy="0 0 0"'),
    "origin not numbers": _with(3, origin='xyz="a b c" rpy="0 0 0"'),
    "zero axis": _with(2, axis="0 0 0"),
    "NaN axis": _with(2, axis="nan 0 1"),
    "limits reversed": _with(3, limit='lower="3" upper="-3" effort="0" velocity="0"'),
    "NaN limit": _with(3, limit='lower="nan" upper="3" effort="0" velocity="0"'),
    "mimic joint": _with(3, extra='<mimic joint="j2" multiplier="1" offset="0"/>'),
    "floating joint": _with(4, kind="floating"),
    "planar joint": _with(4, kind="planar"),
    "prismatic joint": _with(2, kind="prismatic"),
    "duplicate link": chain(
        links=[*LINKS6, "l3"],
        joints=[_joint(k, LINKS6[k - 1], LINKS6[k]) for k in range(1, 7)],
    ),
    "duplicate joint": chain(
        links=LINKS6, joints=[_joint(k, LINKS6[k - 1], LINKS6[k], name="j") for k in range(1, 7)]
    ),
    "no joint at all": chain(links=["base_link", "tool0"], joints=[]),
    "13 revolute joints": chain(13),
    "500 joints": chain(500),
    "2000 links": chain(links=[f"l{k}" for k in range(2000)], joints=[]),
    "deep nesting": "<robot name='r'>" + "<a>" * 50000 + "</a>" * 50000 + "</robot>",
    "1 MB name": f'<robot name="{"x" * 1_000_000}"><link name="base_link"/></robot>',
}


@pytest.fixture
def joints(tmp_path: Path) -> Path:
    out = tmp_path / "joints.csv"
    out.write_text(JOINTS)
    return out


def _write(tmp_path: Path, case: str) -> Path:
    path = tmp_path / "robot.urdf"
    text = CASES[case]
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def _limited() -> None:
    """The child's address space: 3 GiB (the reader needs a few hundred MB)."""
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", list(CASES))
def test_a_hostile_urdf_is_one_line_and_exit_2(tmp_path, joints, case):
    path = _write(tmp_path, case)
    args = ["predict", "--model", str(path), "--joints", str(joints)]
    if case in ("500 joints", "2000 links", "huge origin"):
        # In a child with bounded memory (a 500-joint file once took more than 5 GB),
        # where numpy's warnings would reach stderr.
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        run = subprocess.run(
            [sys.executable, "-m", "cellcal", *args],
            capture_output=True,
            text=True,
            timeout=90,
            preexec_fn=_limited,
            env=env,
        )
    else:
        run = cellcal(*args)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("cellcal: error: "), run.stderr[-2000:]
    assert str(path) in lines[0], lines[0]
    assert len(lines[0]) < 2000, lines[0][:300]


def test_the_bounds_are_named(tmp_path, joints):
    for case, said in (("500 joints", "at most"), ("13 revolute joints", "at most 12")):
        line = cellcal("predict", "--model", _write(tmp_path, case), "--joints", joints).stderr
        assert said in line, line
    line = cellcal("predict", "--model", _write(tmp_path, "billion laughs"), "--joints", joints)
    assert "DTD" in line.stderr or "entit" in line.stderr, line.stderr


def test_a_good_urdf_still_reads(tmp_path, joints):
    """The UR5 of ros-industrial (a DOCTYPE-free file with comments, gazebo tags and
    fixed frames) and a clean six-joint chain are read."""
    ur5 = Path(__file__).parent / "data" / "urdf" / "ur5_robot.urdf"
    assert cellcal("predict", "--model", ur5, "--joints", joints).returncode == 0
