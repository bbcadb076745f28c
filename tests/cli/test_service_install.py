"""``cellcal service install``: the unit rendered for this installation passes
``systemd-analyze verify`` with nothing on stderr (and a unit with an unknown key does
not), is written only where asked, never replaced silently, and nothing is created
for a user that does not exist."""

from __future__ import annotations

import contextlib
import grp
import os
import pwd
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

from cellcal.commands.service import _blocked
from cellcal.service.unitfile import render, render_check, template, verify
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
    # the unit is outside systemd's search path: enable it by its path, where it went
    unit_path = tmp_path.resolve() / "cellcal.service"
    assert f"sudo systemctl daemon-reload && sudo systemctl enable {unit_path}\n" in out
    assert "sudo systemctl start cellcal.service" in out
    assert "usermod" not in out and "-aG root" not in out  # no group advice for root
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


def test_the_rendered_headers_are_about_the_rendered_units() -> None:
    venv, config = Path("/opt/cellcal-with-a-long-name/venv"), Path("/etc/cellcal/cell.toml")
    units = {"cellcal.service": render(venv, config, "cellcal")}
    units.update(render_check(venv, config, "cellcal", "7d"))
    for name, text in units.items():
        header = text[: text.index("[Unit]")]
        assert "are filled in" not in header and "${" not in header, name
        flat = " ".join(line.removeprefix("# ") for line in header.splitlines())
        assert "Rendered by `cellcal service install`" in flat, name
        assert f"venv {venv}," in flat and f"configuration {config}," in flat, name
        assert "user cellcal" in flat, name
        assert all(line.startswith("# ") for line in header.splitlines()), name


def _other_user() -> pwd.struct_passwd:
    """A user other than root and us whose group has its name (as the unit needs)."""
    for u in pwd.getpwall():
        if u.pw_uid in (0, os.getuid()):
            continue
        with contextlib.suppress(KeyError):
            if grp.getgrnam(u.pw_name).gr_gid == u.pw_gid:
                return u
    pytest.skip("no system user with a group of its name")


def test_a_venv_the_services_user_cannot_execute_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    user = _other_user().pw_name
    locked = tmp_path / "locked"
    (locked / "venv" / "bin").mkdir(parents=True)
    exe = locked / "venv" / "bin" / "cellcal"
    exe.write_text("#!/usr/bin/env python3\n")
    exe.chmod(0o755)
    locked.chmod(0o700)
    args = ["service", "install", "--config", CONFIG, "--user", user, "--venv", locked / "venv"]
    for extra in (["--unit-dir", tmp_path], ["--dry-run"]):
        code, out, err = run(capsys, *args, *extra)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"user {user} cannot execute {exe}" in err and str(locked / "venv") in err
        assert "not searchable" in err and out == ""
    assert not (tmp_path / "cellcal.service").exists()


def test_every_folder_on_the_path_is_checked_for_that_users_x_bit(tmp_path: Path) -> None:
    top = Path(tempfile.mkdtemp(prefix="cellcal-x-"))  # under /tmp, 0700, ours
    try:
        exe = top / "bin" / "cellcal"
        exe.parent.mkdir()
        exe.write_text("")
        exe.chmod(0o750)
        st = top.stat()
        other, group = st.st_uid + 4242, st.st_gid
        assert _blocked(exe, other, {group + 4242}) == top  # other: no x on top
        top.chmod(0o710)
        assert _blocked(exe, other, {group}) is None  # the group's bits
        assert _blocked(exe, other, {group + 4242}) == top
        top.chmod(0o711)
        assert _blocked(exe, other, {group + 4242}) == exe  # a file other cannot run
        exe.chmod(0o755)
        assert _blocked(exe, other, {group + 4242}) is None
        assert _blocked(exe, st.st_uid, set()) is None  # the owner
        exe.chmod(0o644)
        assert _blocked(exe, 0, set()) == exe  # root needs one x bit on a file
    finally:
        shutil.rmtree(top)
