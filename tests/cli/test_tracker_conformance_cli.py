"""``cellcal tracker --address ADDR --conformance [--json]`` (issue 31): one line per check,
exit 0 when every check holds, 1 when one does not (the specs give conformance no code of
its own: docs/tracker.md), 2 and one line when it cannot run. Against the twin and a
broken bridge on 127.0.0.29 (listening before the command runs)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.mocks.tracker.server import TrackerTwin
from tests.drivers.test_tracker_conformance import V1_CHECKS, V2_CHECKS, Bridge
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60)]

HOST = "127.0.0.29"


class Still:
    def sample(self, n: int) -> np.ndarray:
        return np.tile([1000.0, 200.0, 300.0], (n, 1))


def test_the_twin_conforms_in_words_and_in_json():
    with TrackerTwin(Still(), time_scale=0.01) as twin:
        host, port = twin.start_tcp(HOST, 0)  # returns once listening
        address = f"socket://{host}:{port}"
        done = cellcal("tracker", "--address", address, "--conformance", "--timeout", "2")
        assert done.returncode == 0, done.stderr
        lines = done.stdout.splitlines()
        assert lines[0] == (
            f"tracker cellcal,mock-tracker,SIM-0001,1.0 at {address}: line protocol version 1, 2"
        )
        assert [line.split(":")[0] for line in lines[1:-1]] == [
            f"ok    {name}" for name in [*V1_CHECKS, *V2_CHECKS, "new connection in version 1"]
        ]
        assert lines[-1] == "all 19 checks hold"
        assert done.stderr == f"cellcal tracker: checking the line protocol of {address}\n"
        done = cellcal("tracker", "--url", address, "--conformance", "--json", "--timeout", "2")
        assert done.returncode == 0, done.stderr
        out = json.loads(done.stdout)
        assert out["passed"] is True and out["failed"] == [] and out["versions"] == [1, 2]
        assert out["idn"] == "cellcal,mock-tracker,SIM-0001,1.0" and out["address"] == address
        assert len(out["checks"]) == 19 and all(c["ok"] for c in out["checks"])
        assert set(out["checks"][0]) == {"name", "ok", "expected", "got"}


def test_measuring_reports_the_version_and_the_air():
    """Without --conformance: the version the tracker announces, its covariance and air."""
    with TrackerTwin(Still()) as twin:
        host, port = twin.start_tcp(HOST, 0)
        done = cellcal(
            "tracker", "--address", f"socket://{host}:{port}", "--samples", "3", "--json"
        )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["protocol"] == 2 and out["n"] == 3
    assert (out["temperature_c"], out["pressure_hpa"], out["humidity_pct"]) == (20.0, 1013.25, 45.0)
    np.testing.assert_allclose(out["cov_mm2"], np.eye(3) * 1e-4 / 3)


def test_a_broken_bridge_exits_1_and_says_what_it_got_wrong():
    with Bridge(HOST, "busy-restarts") as bridge:
        done = cellcal("tracker", "--address", bridge.address, "--conformance", "--timeout", "1")
        assert done.returncode == 1, done.stderr
        fail = [line for line in done.stdout.splitlines() if line.startswith("FAIL")]
        assert fail == [
            "FAIL  MEAS while busy: expected ERR 1 BUSY to 'MEAS 1 10', got OK 1",
        ], done.stdout
        assert done.stdout.splitlines()[-1] == "1 of 19 checks failed: MEAS while busy"
        done = cellcal(
            "tracker", "--address", bridge.address, "--conformance", "--json", "--timeout", "1"
        )
    assert done.returncode == 1, done.stderr
    out = json.loads(done.stdout)
    assert out["passed"] is False and out["failed"] == ["MEAS while busy"]
    (failed,) = [c for c in out["checks"] if not c["ok"]]
    assert failed == {
        "name": "MEAS while busy",
        "ok": False,
        "expected": "ERR 1 BUSY to 'MEAS 1 10'",
        "got": "OK 1",
    }


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (
            ["--address", "127.0.0.29:700", "--dialect", "emscon", "--conformance"],
            "--conformance: for the line protocol (--dialect line-protocol)",
        ),
        (
            ["--address", "socket://127.0.0.29:9", "--conformance", "--timeout", "1"],
            "tracker at socket://127.0.0.29:9: ",
        ),
        (["--address", "spy://socket://127.0.0.29:9", "--conformance"], "refused"),
    ],
)
def test_when_it_cannot_run_it_is_one_line_and_exit_2(args, says):
    done = cellcal("tracker", *args)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("cellcal:")]
    assert len(errors) == 1 and says in errors[0], done.stderr
    assert done.stderr.strip().splitlines()[-1] == errors[0] and done.stdout == ""


def test_a_mute_device_is_one_line_and_exit_2():
    with Bridge(HOST, "mute") as bridge:
        done = cellcal("tracker", "--address", bridge.address, "--conformance", "--timeout", "0.5")
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == (
        f"cellcal: error: tracker at {bridge.address}: no answer to '*IDN?' within 0.5 s: is it "
        "a tracker or bridge that speaks the line protocol?"
    )
