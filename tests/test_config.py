"""Configuration files: the bundled cells, and every way a file can be wrong."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.config import ConfigError, config_from_dict, load_config

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
    (folder / "cell.toml").write_text(text)
    config = load_config(folder / "cell.toml")
    assert config.robot.model == str(folder / "robot.toml")
    assert config.storage.database == str(folder / "cellcal.db")
