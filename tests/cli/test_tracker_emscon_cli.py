"""``cellcal mock tracker --dialect emscon`` and ``cellcal tracker --dialect emscon``
(the contract of docs/tracker.md): the twin in a process of its own on 127.0.0.253, the
measuring command against it, and the refusals, each one line."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(120)]

MOCK = (sys.executable, "-m", "cellcal", "mock", "tracker", "--dialect", "emscon")


def test_measure_once_from_the_emscon_twin(tmp_path: Path):
    twin = subprocess.Popen(
        [*MOCK, "--listen", "127.0.0.253:0", "--time-scale", "0.01"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert twin.stdout is not None
        address = twin.stdout.readline().strip()  # printed once it listens
        assert address.startswith("127.0.0.253:"), twin.stderr.read() if twin.stderr else ""
        done = cellcal("tracker", "--address", address, "--dialect", "emscon")
        assert done.returncode == 0, done.stderr
        assert "Leica,AT401" in done.stdout and "air 20.00 °C" in done.stdout
        done = cellcal(
            "tracker", "--address", address, "--dialect", "emscon", "--samples", "3", "--json"
        )
        assert done.returncode == 0, done.stderr
        out = json.loads(done.stdout)
        assert out["n"] == 3 and out["idn"].startswith("Leica,AT401,")
        cov = out["cov_mm2"]
        assert len(cov) == 3 and all(len(row) == 3 for row in cov) and cov[0][0] > 0
        assert (out["temperature_c"], out["pressure_hpa"]) == (20.0, 1013.25)
    finally:
        twin.send_signal(signal.SIGTERM)
        twin.communicate(timeout=30)
    assert twin.returncode == 0


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["tracker"], "give the tracker's --address (or --url), once"),
        (["tracker", "--address", "a", "--url", "b"], "give the tracker's --address"),
        (["mock", "tracker", "--dialect", "emscon", "--pty"], "--pty: for the line protocol"),
        (
            [*MOCK[3:], "--listen", "127.0.0.253:0", "--garbage-every", "3"],
            "--garbage-every: for the line protocol",
        ),
        (
            ["tracker", "--address", "127.0.0.253:9", "--dialect", "emscon", "--timeout", "2"],
            "tracker at 127.0.0.253:9: cannot connect",
        ),
        (  # TPI's default port, named in the line
            ["tracker", "--address", "127.0.0.253", "--dialect", "emscon", "--timeout", "2"],
            "tracker at 127.0.0.253:700: cannot connect",
        ),
    ],
)
def test_refusals_are_one_line(args, says):
    done = cellcal(*args)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], done.stderr
