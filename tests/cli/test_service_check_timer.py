"""``cellcal service install --check-every``: a timer and a one-shot service that queue
a check between calibrations in the cell service, rendered for the installation, passing
``systemd-analyze verify`` with the service's unit, written beside it and never replaced
silently; a span systemd would not take is one line."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from cellcal.errors import CampaignError
from cellcal.service.unitfile import CHECK_SERVICE, CHECK_TIMER, render, render_check, verify
from tests.cli.test_calibrate_cli import run
from tests.cli.test_service_install import CONFIG, needs_analyze

VENV = Path(sys.prefix)


def test_the_timer_and_its_service_are_filled_in() -> None:
    units = render_check(VENV, CONFIG, "cellcal", "7d")
    timer, service = units[CHECK_TIMER], units[CHECK_SERVICE]
    assert "${" not in timer + service
    assert "\nOnUnitActiveSec=7d\n" in timer and "\nUnit=cellcal-check.service\n" in timer
    assert "\nWantedBy=timers.target\n" in timer
    start = f"ExecStart={VENV}/bin/cellcal campaign start --kind check --queue --socket "
    assert start + "/run/cellcal/control.sock\n" in service
    assert "\nType=oneshot\n" in service and "\nRequires=cellcal.service\n" in service
    assert "\nUser=cellcal\n" in service
    assert "OnUnitActiveSec=2d 12h\n" in render_check(VENV, CONFIG, "u", " 2d   12h")[CHECK_TIMER]
    for bad in ("7", "weekly", "7d; rm -rf /", "-1d", ""):
        with pytest.raises(CampaignError, match="a systemd time span"):
            render_check(VENV, CONFIG, "cellcal", bad)


@needs_analyze
def test_systemd_analyze_verify_takes_the_three_units_and_catches_a_bad_one() -> None:
    units = render_check(VENV, CONFIG, "root", "7d")
    checked = verify(render(VENV, CONFIG, "root"), others=units)
    assert checked.ran and checked.ok, checked.message
    broken = {**units, CHECK_TIMER: units[CHECK_TIMER].replace("OnBootSec", "OnBootSecs")}
    checked = verify(render(VENV, CONFIG, "root"), others=broken)
    assert not checked.ok and "OnBootSecs" in checked.message


@needs_analyze
def test_install_writes_the_timer_beside_the_unit(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    args = ["service", "install", "--config", CONFIG, "--user", "root", "--unit-dir", tmp_path]
    code, out, err = run(capsys, *args, "--check-every", "7d")
    assert code == 0, err
    units = render_check(VENV, CONFIG, "root", "7d")
    for name, text in units.items():
        assert (tmp_path / name).read_text() == text
        assert f"{tmp_path / name}: written" in out
    where = tmp_path.resolve()
    assert f"sudo systemctl link {where / CHECK_SERVICE}\n" in out
    assert f"sudo systemctl enable --now {where / CHECK_TIMER}\n" in out
    # another span: the timer differs and is not replaced silently, nothing is written
    code, _, err = run(capsys, *args, "--check-every", "1d")
    assert code == 2 and "cellcal-check.timer exists and differs" in err
    assert (tmp_path / CHECK_TIMER).read_text() == units[CHECK_TIMER]
    code, _, err = run(capsys, *args, "--check-every", "fortnightly")
    assert code == 2 and err.count("\n") == 1 and "a systemd time span" in err
