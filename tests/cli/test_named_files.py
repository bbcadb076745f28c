"""The files a configuration names (a rig's calibration and target, an ABB
controller's credentials) are checked where a missing one would otherwise surface only
as a device that never connects: ``cellcal service install`` and the service's start
refuse in one line naming the key (exit 2), and nothing is written."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

from cellcal.config import load_config
from cellcal.config_files import check_named_files
from cellcal.errors import ConfigError
from tests.cli.test_calibrate_cli import run

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"


def _cell(folder: Path, *files: str) -> Path:
    """The bundled rig cell copied into ``folder`` with only ``files`` beside it."""
    shutil.copy(CONFIG / "mock-cell.toml", folder / "cell.toml")
    for name in files:
        shutil.copy(CONFIG / name, folder / name)
    return folder / "cell.toml"


def test_the_bundled_cell_names_files_that_exist(tmp_path: Path) -> None:
    path = _cell(tmp_path, "mock-rig.toml", "mock-target.toml")
    check_named_files(load_config(path), str(path))  # nothing refused


@pytest.mark.parametrize(
    ("present", "key", "why"),
    [
        ((), "sensor.2.rig_file", "no such file"),
        (("mock-rig.toml",), "sensor.2.target_file", "no such file"),
    ],
    ids=["rig", "target"],
)
def test_a_missing_file_is_named_by_its_key(
    tmp_path: Path, present: tuple[str, ...], key: str, why: str
) -> None:
    path = _cell(tmp_path, *present)
    with pytest.raises(ConfigError) as exc:
        check_named_files(load_config(path), "cell.toml")
    assert str(exc.value).startswith(f"cell.toml: {key} = {tmp_path}/")
    assert str(exc.value).endswith(f": {why}") and "\n" not in str(exc.value)


def test_a_folder_where_the_file_should_be_is_refused(tmp_path: Path) -> None:
    path = _cell(tmp_path, "mock-target.toml")
    (tmp_path / "mock-rig.toml").mkdir()
    with pytest.raises(ConfigError, match=r"sensor\.2\.rig_file = .*mock-rig\.toml: not a file$"):
        check_named_files(load_config(path), "cell.toml")


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads every file")
def test_an_unreadable_file_is_refused(tmp_path: Path) -> None:
    path = _cell(tmp_path, "mock-rig.toml", "mock-target.toml")
    (tmp_path / "mock-target.toml").chmod(0)
    with pytest.raises(ConfigError, match=r"target_file = .*: not readable by this user$"):
        check_named_files(load_config(path), "cell.toml")


def test_an_abb_controllers_credentials_file_is_checked(tmp_path: Path) -> None:
    path = tmp_path / "abb.toml"
    text = (CONFIG / "mock-cell-tracker.toml").read_text()
    robot = '[robot]\ndriver = "abb-rws"\naddress = "http://10.0.0.9"\ncredentials = "rws.txt"\n'
    head, _, rest = text.partition("[robot]\n")
    path.write_text(head + robot + rest.partition("\n\n")[2])
    with pytest.raises(ConfigError, match=r"robot\.credentials = .*/rws\.txt: no such file$"):
        check_named_files(load_config(path), "abb.toml")
    (tmp_path / "rws.txt").write_text("Default User\nrobotics\n")
    check_named_files(load_config(path), "abb.toml")


def test_service_install_refuses_a_missing_rig_file(tmp_path: Path, capsys) -> None:
    path = _cell(tmp_path, "mock-target.toml")
    code, out, err = run(
        capsys, "service", "install", "--dry-run", "--config", path, "--venv", sys.prefix
    )
    assert code == 2 and out == ""
    assert err.splitlines() == [
        f"cellcal: error: {path}: sensor.2.rig_file = {tmp_path}/mock-rig.toml: no such file"
    ]


def test_the_service_does_not_start_on_a_missing_rig_file(tmp_path: Path, capsys) -> None:
    path = _cell(tmp_path, "mock-target.toml")
    db, sock = tmp_path / "c.db", tmp_path / "run" / "control.sock"
    code, out, err = run(capsys, "daemon", "--mock", "--config", path, "--db", db, "--socket", sock)
    assert code == 2 and out == ""
    assert err.splitlines() == [
        f"cellcal: error: {path}: sensor.2.rig_file = {tmp_path}/mock-rig.toml: no such file"
    ]
    assert not db.exists() and not sock.parent.exists()  # refused before anything is made
