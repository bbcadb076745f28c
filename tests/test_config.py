"""Configuration files: the bundled cells, and every way a file can be wrong."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cellcal.config import config_from_dict, load_config
from cellcal.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_bundled_and_example_configs_load():
    mock = load_config(ROOT / "config" / "mock-cell.toml")
    assert mock.robot.model == "kuka-kr5-arc"
    assert [s.name for s in mock.sensor] == ["tracker", "rig"]
    assert mock.reference_sensor.name == "tracker"
    assert mock.campaign.dwell_s == 7.0 and mock.campaign.samples_per_pose == 20
    assert mock.campaign.grid == [4, 4, 5]
    # The package ships the same file.
    packaged = ROOT / "cellcal" / "data" / "mock-cell.toml"
    assert packaged.read_text() == (ROOT / "config" / "mock-cell.toml").read_text()
    example = load_config(ROOT / "config" / "cell.example.toml")
    assert example.campaign.cube_edge_mm == 200.0


def _base(**over):
    data = {"sensor": [{"name": "tracker", "kind": "laser-tracker", "reference": True}]}
    data.update(over)
    return data


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (_base(campaign={"dwel_s": 7}), r"x.toml: campaign.dwel_s: unknown key"),
        (_base(robot={"speed": 2.0}), r"robot.speed: Input should be less than or equal to 1"),
        (_base(campaign={"grid": [4, 4]}), r"campaign.grid"),
        (_base(campaign={"samples_per_pose": "20"}), r"samples_per_pose"),
        (
            _base(campaign={"workspace_min_mm": [0, 0, 0], "workspace_max_mm": [1, 1, -1]}),
            "workspace_min_mm",
        ),
        ({"sensor": []}, "sensor"),
        ({"sensor": [{"name": "t", "kind": "laser-tracker"}]}, "exactly one sensor"),
        (
            {"sensor": [{"name": "t", "kind": "laser-tracker", "reference": True}] * 2},
            "unique",
        ),
        (
            _base(sensor=[{"name": "t t", "kind": "laser-tracker", "reference": True}]),
            r"sensor.0.name",
        ),
        (_base(sensor=[{"name": "t", "kind": "radar", "reference": True}]), r"sensor.0.kind"),
        (_base(colour="red"), "colour: unknown key"),
    ],
)
def test_bad_configs_name_the_key(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data, "x.toml")


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot\nmodel = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="directory"):
        load_config(tmp_path)


def test_relative_paths_resolve_against_the_config_folder(tmp_path):
    from pathlib import Path

    from cellcal.config import load_config

    bundled = Path(__file__).parents[1] / "config" / "mock-cell.toml"
    folder = tmp_path / "cell"
    folder.mkdir()
    (folder / "robot.toml").write_text(
        (
            Path(__file__).parents[1] / "cellcal" / "data" / "models" / "kuka-kr5-arc.toml"
        ).read_text()
    )
    text = bundled.read_text().replace('model = "kuka-kr5-arc"', 'model = "robot.toml"', 1)
    assert 'model = "robot.toml"' in text
    (folder / "cell.toml").write_text(text + '\n[storage]\ndatabase = "cellcal.db"\n')
    config = load_config(folder / "cell.toml")
    assert config.robot.model == str(folder.resolve() / "robot.toml")
    assert config.storage.database == str(folder.resolve() / "cellcal.db")


# ------------------------------------------------------------ keys of earlier versions

#: A cell's file as versions before the device families wrote it (config/cell.example.toml
#: of then, with a tracker alone: the rig's noise model is gone), and the same cell today.
OLD_CELL = """
name = "cell 7"
[robot]
model = "kuka-kr5-arc"
driver = "modbus"
address = "192.168.1.20"
settle_timeout_s = 60.0     # read for UR robots only
[robot.modbus]
port = 1502
device_id = 3
word_order = "little"
heartbeat = 4
status = 7
error = 2
ack = 3
timeout_s = 45.0
[[sensor]]
name = "tracker"
kind = "laser-tracker"
driver = "simulated"
url = "socket://10.0.0.5:5555"
reference = true
[campaign]
grid = [2, 2, 2]
validation_inside = 2
validation_per_region = 1
[simulation]
seed = 7
rig_noise_mm = 0.05
"""
NEW_CELL = """
name = "cell 7"
[robot]
model = "kuka-kr5-arc"
driver = "modbus"
address = "192.168.1.20:1502"
move_timeout_s = 45.0
[robot.map]
device_id = 3
word_order = "little"
heartbeat = 4
status = 7
error_code = 2
ack = 3
[[sensor]]
name = "tracker"
kind = "laser-tracker"
driver = "line-protocol"
address = "socket://10.0.0.5:5555"
reference = true
[campaign]
grid = [2, 2, 2]
validation_inside = 2
validation_per_region = 1
[simulation]
seed = 7
"""
OLD_WARNINGS = [
    'robot.settle_timeout_s is deprecated, ignored: it timed the moves of driver = "ur" only',
    "[robot.modbus] is deprecated, read as [robot.map]; rename the table [robot.map]",
    "robot.modbus.error is deprecated, read as robot.map.error_code; write error_code = 2",
    "robot.modbus.timeout_s is deprecated, read as robot.move_timeout_s; "
    "write move_timeout_s = 45.0",
    'robot.modbus.port is deprecated, read as robot.address; write address = "192.168.1.20:1502"',
    "sensor.0.url is deprecated, read as sensor.0.address; "
    'write address = "socket://10.0.0.5:5555"',
    'sensor.0.driver = "simulated" is deprecated, read as "line-protocol"',
    "simulation.rig_noise_mm is deprecated, ignored: the rig's images are rendered",
]


def _warnings(stderr: str, path: Path) -> list[str]:
    lines = stderr.splitlines()
    prefix = f"cellcal: warning: {path}: "
    assert all(line.startswith(prefix) for line in lines), lines
    return [line.removeprefix(prefix) for line in lines]


def _matches(lines: list[str], expected: list[str]) -> bool:
    """One line for each expected one, in order, each beginning with it."""
    assert len(lines) == len(expected), lines
    for line, start in zip(lines, expected, strict=True):
        assert line.startswith(start), (line, start)
    return True


def test_an_old_file_is_read_as_its_new_twin_with_one_warning_a_key(tmp_path, capsys):
    old, new = tmp_path / "old.toml", tmp_path / "new.toml"
    old.write_text(OLD_CELL)
    new.write_text(NEW_CELL)
    today = load_config(new)
    assert capsys.readouterr().err == ""
    assert load_config(old) == today
    assert _matches(_warnings(capsys.readouterr().err, old), OLD_WARNINGS)
    assert today.robot.map.status == 7 and today.robot.move_timeout_s == 45.0
    # The same keys from a dictionary (a file sent to the service) warn through `warn`.
    lines: list[str] = []
    data = tomllib.loads(OLD_CELL)
    assert config_from_dict(data, "sent.toml", warn=lines.append) == config_from_dict(
        tomllib.loads(NEW_CELL), "x"
    )
    assert _matches([x.removeprefix("sent.toml: ") for x in lines], OLD_WARNINGS)
    assert data == tomllib.loads(OLD_CELL)  # the caller's data is left as it was


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        # the example: url, in a robot's table as in a sensor's
        (
            '[robot]\ndriver = "modbus"\nurl = "10.0.0.9"\n',
            '[robot]\ndriver = "modbus"\naddress = "10.0.0.9"\n',
            ['robot.url is deprecated, read as robot.address; write address = "10.0.0.9"'],
        ),
        # a UR's settle timeout is its move timeout; the Modbus table every robot had is
        # ignored by a UR, as it always was
        (
            '[robot]\nmodel = "ur10e"\ndriver = "ur"\naddress = "10.0.0.9"\n'
            "settle_timeout_s = 30.0\n[robot.modbus]\nport = 502\n",
            '[robot]\nmodel = "ur10e"\ndriver = "ur"\naddress = "10.0.0.9"\n'
            "move_timeout_s = 30.0\n",
            [
                "robot.settle_timeout_s is deprecated, read as robot.move_timeout_s; "
                "write move_timeout_s = 30.0",
                '[robot.modbus] is deprecated, ignored: it mapped driver = "modbus" only '
                '(this robot: "ur"); delete it',
            ],
        ),
        # a port the address names already, an IPv6 host given one in brackets
        (
            '[robot]\ndriver = "modbus"\naddress = "h:1502"\n[robot.modbus]\nport = 1502\n',
            '[robot]\ndriver = "modbus"\naddress = "h:1502"\n',
            [
                "[robot.modbus] is deprecated, read as [robot.map]",
                'robot.modbus.port is deprecated, and robot.address "h:1502" names it already',
            ],
        ),
        (
            '[robot]\ndriver = "modbus"\naddress = "fd00::7"\n[robot.modbus]\nport = 1502\n',
            '[robot]\ndriver = "modbus"\naddress = "[fd00::7]:1502"\n',
            [
                "[robot.modbus] is deprecated, read as [robot.map]",
                'robot.modbus.port is deprecated, read as robot.address; write address = "[fd00',
            ],
        ),
        # url with the old table's port: both lines name the address that is read
        (
            '[robot]\ndriver = "modbus"\nurl = "10.0.0.9"\n[robot.modbus]\nport = 1502\n',
            '[robot]\ndriver = "modbus"\naddress = "10.0.0.9:1502"\n',
            [
                'robot.url is deprecated, read as robot.address; write address = "10.0.0.9:1502"',
                "[robot.modbus] is deprecated, read as [robot.map]",
                "robot.modbus.port is deprecated, read as robot.address; write address = "
                '"10.0.0.9:1502"',
            ],
        ),
    ],
    ids=["robot-url", "ur-settle", "port-named", "ipv6", "url-and-port"],
)
def test_each_earlier_key_is_read_as_todays(tmp_path, capsys, old, new, expected):
    tracker = '[[sensor]]\nname = "t"\nkind = "laser-tracker"\nreference = true\n'
    (tmp_path / "old.toml").write_text(old + tracker)
    (tmp_path / "new.toml").write_text(new + tracker)
    today = load_config(tmp_path / "new.toml")
    assert load_config(tmp_path / "old.toml") == today
    assert _matches(_warnings(capsys.readouterr().err, tmp_path / "old.toml"), expected)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cellcal", *args], capture_output=True, text=True, timeout=120
    )


def test_cellcal_plan_reads_an_old_file(tmp_path):
    old, new = tmp_path / "old.toml", tmp_path / "new.toml"
    old.write_text(OLD_CELL)
    new.write_text(NEW_CELL)
    runs = {p: _cli("plan", "--config", str(p), "--json") for p in (old, new)}
    assert runs[old].returncode == 0, runs[old].stderr
    assert runs[new].returncode == 0 and runs[new].stderr == ""
    assert _matches(_warnings(runs[old].stderr, old), OLD_WARNINGS)  # once each
    plans = {p: json.loads(run.stdout) for p, run in runs.items()}
    assert plans[old].pop("config") == str(old) and plans[new].pop("config") == str(new)
    assert plans[old] == plans[new]


MIXED = [
    ('[robot]\naddress = "a"\nurl = "b"\n', r"robot\.url is deprecated and robot\.address replaces it; both are given \(keep robot\.address only\)"),  # noqa: E501
    ('[robot]\ndriver = "modbus"\n[robot.modbus]\nack = 3\n[robot.map]\nack = 3\n', r"\[robot\.modbus\] is deprecated and \[robot\.map\] replaces it"),  # noqa: E501
    ('[robot]\ndriver = "modbus"\n[robot.modbus]\nerror = 2\nerror_code = 2\n', r"robot\.modbus\.error is deprecated and robot\.map\.error_code replaces it"),  # noqa: E501
    ('[robot]\ndriver = "modbus"\nmove_timeout_s = 9.0\n[robot.modbus]\ntimeout_s = 9.0\n', r"robot\.modbus\.timeout_s is deprecated and robot\.move_timeout_s replaces it"),  # noqa: E501
    ('[robot]\ndriver = "ur"\nsettle_timeout_s = 9.0\nmove_timeout_s = 9.0\n', r"robot\.settle_timeout_s is deprecated and robot\.move_timeout_s replaces it"),  # noqa: E501
    ('[robot]\ndriver = "modbus"\naddress = "h:502"\n[robot.modbus]\nport = 1502\n', r"robot\.modbus\.port = 1502 is deprecated and robot\.address \"h:502\" names port 502; keep robot\.address only"),  # noqa: E501
    ('[simulation]\nrig_noise_mm = 0.1\nrig_noise_grey = 2.0\n', r"simulation\.rig_noise_mm is deprecated and simulation\.rig_noise_grey replaces it"),  # noqa: E501
    ('[[sensor]]\nname = "u"\nkind = "laser-tracker"\nurl = "a"\naddress = "a"\n', r"sensor\.1\.url is deprecated and sensor\.1\.address replaces it"),  # noqa: E501
]  # fmt: skip


@pytest.mark.parametrize(
    ("text", "match"),
    MIXED,
    ids=["url", "map", "error", "timeout", "settle", "port", "rig-noise", "sensor-url"],
)
def test_an_old_key_with_its_new_one_is_refused(tmp_path, capsys, text, match):
    path = tmp_path / "mixed.toml"
    path.write_text('[[sensor]]\nname = "t"\nkind = "laser-tracker"\nreference = true\n' + text)
    with pytest.raises(ConfigError, match=f"^{re.escape(str(path))}: {match}"):
        load_config(path)
    assert capsys.readouterr().err == ""  # the refusal alone, no warning before it


def test_cellcal_refuses_a_mixed_file_in_one_line(tmp_path):
    path = tmp_path / "mixed.toml"
    path.write_text(OLD_CELL.replace('url = "socket', 'address = "socket://h:1"\nurl = "socket'))
    run = _cli("plan", "--config", str(path))
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr == (
        f"cellcal: error: {path}: sensor.0.url is deprecated and sensor.0.address replaces it; "
        "both are given (keep sensor.0.address only)\n"
    )


@pytest.mark.parametrize(
    ("data", "match"),
    [
        # an old key where it never was is an unknown key, as any other
        (_base(campaign={"url": "x"}), r"campaign\.url: unknown key \(renamed: address\)"),
        (_base(robot={"driver": "modbus", "modbus": 1}), r"robot\.modbus: unknown key"),
        (_base(robot={"driver": "modbus", "map": {"error": 2}}), r"robot\.map\.error: unknown key"),
        (_base(robot={"driver": "modbus", "modbus": {"port": 0}}), r"robot\.modbus\.port: a port"),
        (_base(robot={"driver": "modbus", "modbus": {"colour": 1}}), r"robot\.map\.colour: unknown"),  # noqa: E501
        (_base(sensor=[{"name": "r", "kind": "photogrammetry", "driver": "simulated", "reference": True}]), r"sensor\.0\.driver = \"simulated\" was the noise model"),  # noqa: E501
    ],
)  # fmt: skip
def test_other_unknown_keys_stay_errors(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data, "x.toml")


def test_the_campaign_region_is_the_cube_unless_set():
    assert config_from_dict(_base(), "x.toml").campaign.region == "cube"
    box = config_from_dict(_base(campaign={"region": "workspace"}), "x.toml")
    assert box.campaign.region == "workspace"
    with pytest.raises(ConfigError, match=r"x.toml: campaign.region: .*'cube' or 'workspace'"):
        config_from_dict(_base(campaign={"region": "box"}), "x.toml")
