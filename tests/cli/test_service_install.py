"""``cellcal service install``: the unit rendered for this installation passes
``systemd-analyze verify`` with nothing on stderr (and a unit with an unknown key does
not), is written only where asked, never replaced silently, and nothing is created
for a user that does not exist."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from cellcal.daemon.unitfile import render, template, verify
from tests.cli.test_calibrate_cli import run

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "mock-cell-tracker.toml"
VENV = Path(sys.prefix)
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(
    ANALYZE is None, reason="systemd-analyze is not installed (make test installs systemd)"
)


def test_the_template_in_the_package_is_the_config_folders() -> None:
    assert template() == (ROOT / "config" / "cellcal.service").read_text()


def test_render_fills_every_field() -> None:
    text = render(VENV, CONFIG, "cellcal")
    assert "${" not in text
    assert f"ExecStart={VENV}/bin/cellcal daemon --config {CONFIG} " in text
    assert "ExecReload=/bin/kill -HUP $MAINPID" in text
    for line in ["Type=notify", "NotifyAccess=main", "WatchdogSec=30s", "KillMode=mixed"]:
        assert f"\n{line}\n" in text
    assert "\nUser=cellcal\n" in text and "\nSupplementaryGroups=dialout\n" in text
    home = str(CONFIG).startswith(("/home/", "/root/")) or str(VENV).startswith("/home/")
    assert f"\nProtectHome={'read-only' if home else 'yes'}\n" in text
    assert "\nProtectHome=yes\n" in render(Path("/opt/cellcal"), Path("/etc/cell.toml"), "u")
    for venv, user in [(Path("/opt/cell cal"), "cellcal"), (VENV, "Robert'); DROP")]:
        with pytest.raises(Exception, match=r"--venv|--user"):
            render(venv, CONFIG, user)


@needs_analyze
def test_systemd_analyze_verify_says_nothing_on_the_rendered_unit() -> None:
    checked = verify(render(VENV, CONFIG, "root"))
    assert checked.ran and checked.ok, checked.message


@needs_analyze
def test_systemd_analyze_verify_catches_an_unknown_key() -> None:
    """It exits 0 on an unknown key: the check must read stderr."""
    text = render(VENV, CONFIG, "root").replace("Type=notify\n", "Type=notify\nWatchDogSec=3\n")
    checked = verify(text)
    assert checked.ran and not checked.ok
    assert "WatchDogSec" in checked.message and "\n" not in checked.message
    missing = render(Path("/opt/no-such-venv"), CONFIG, "root")
    assert not verify(missing).ok  # ExecStart names a program that is not there


@needs_analyze
def test_install_dry_run_writes_nothing(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, out, err = run(
        capsys, "service", "install", "--config", CONFIG, "--dry-run", "--unit-dir", tmp_path
    )
    assert code == 0, err
    assert out == render(VENV, CONFIG, "cellcal")
    assert "no complaint" in err and "nothing written" in err
    assert not list(tmp_path.iterdir())


@needs_analyze
def test_install_writes_once_and_never_replaces_silently(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    args = ["service", "install", "--config", CONFIG, "--user", "root", "--unit-dir", tmp_path]
    code, out, err = run(capsys, *args)
    assert code == 0, err
    unit = tmp_path / "cellcal.service"
    assert unit.read_text() == render(VENV, CONFIG, "root")
    assert "written" in out
    assert "sudo systemctl daemon-reload && sudo systemctl enable cellcal.service" in out
    assert "sudo systemctl start cellcal.service" in out
    assert "unchanged" in run(capsys, *args)[1]
    unit.write_text(unit.read_text() + "# edited by hand\n")
    code, out, err = run(capsys, *args)
    assert code == 2 and "exists and differs" in err and len(err.strip().splitlines()) == 1
    assert unit.read_text().endswith("# edited by hand\n")
    assert run(capsys, *args, "--force")[0] == 0
    assert unit.read_text() == render(VENV, CONFIG, "root")


def test_install_refuses_what_it_cannot_use(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    base = ["service", "install", "--unit-dir", tmp_path]
    code, _, err = run(capsys, *base, "--config", tmp_path / "none.toml")
    assert code == 2 and "no such file" in err
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot]\nmodel = 3\n")
    code, _, err = run(capsys, *base, "--config", bad)
    assert code == 2 and "bad.toml" in err
    code, _, err = run(capsys, *base, "--config", CONFIG, "--venv", tmp_path)
    assert code == 2 and "no bin/cellcal" in err
    if ANALYZE is not None:
        code, _, err = run(capsys, *base, "--config", CONFIG, "--user", "no-such-cellcal-user")
        assert code == 2 and "sudo useradd --system --user-group" in err
    assert not list(p for p in tmp_path.iterdir() if p.suffix == ".service")
