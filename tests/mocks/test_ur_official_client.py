"""The UR twin against UR's own RTDE client (UniversalRobots/RTDE_Python_Client_Library),
a client nobody here wrote: it records at the frequency asked (its ``examples/record.py``
with its ``record_configuration.xml`` where a checkout of it is given, else the same
loop on its ``RTDE`` class and CSV writer), every output the twin serves comes through
its unpacking, and it sees an invalid frequency, an unknown field and an input round
trip as a controller makes it see them.

UR's client is not on PyPI; ``make test`` unpacks UR's release 2.7.0 from the OpenUr
wheel on PyPI (tests/mocks/ur_official_client.py says how and why), so CI runs these
tests. ``CELLCAL_UR_RTDE_CLIENT=/path/to/RTDE_Python_Client_Library`` runs them against
a checkout of UR's current release instead. tests/mocks/test_ur_twin_wire.py pins the
same behaviours with raw sockets (docs/ur-twin.md)."""

from __future__ import annotations

import contextlib
import csv
import importlib
import itertools
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from cellcal.config import load_config
from cellcal.files.models import load_model
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.ur.fields import LATER_OUTPUTS, OUTPUT_TYPES
from cellcal.mocks.ur.server import URTwin, twin_for_cell
from tests.mocks.ur_official_client import client_dir

CLIENT = client_dir()
if CLIENT is None:
    pytest.skip(
        "UR's RTDE client is not on PyPI and was not unpacked from the OpenUr wheel "
        "(no network at set-up?); set CELLCAL_UR_RTDE_CLIENT to a checkout of "
        "UniversalRobots/RTDE_Python_Client_Library",
        allow_module_level=True,
    )
if str(CLIENT) not in sys.path:
    sys.path.insert(0, str(CLIENT))
ur_rtde_client: Any = importlib.import_module("rtde.rtde")
ur_config: Any = importlib.import_module("rtde.rtde_config")
ur_csv: Any = importlib.import_module("rtde.csv_writer")

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(120, method="thread")]

EXAMPLES = CLIENT / "examples"
HAS_EXAMPLES = (EXAMPLES / "record.py").is_file()
# The outputs of UR's record_configuration.xml (the RTDE guide's names and types), for
# a client without its examples.
RECORD_OUTPUTS = {
    "timestamp": "DOUBLE",
    **dict.fromkeys(
        [
            "target_q",
            "target_qd",
            "target_qdd",
            "target_current",
            "target_moment",
            "actual_q",
            "actual_qd",
            "actual_current",
            "joint_control_output",
            "actual_TCP_pose",
            "actual_TCP_speed",
            "actual_TCP_force",
            "target_TCP_pose",
            "target_TCP_speed",
        ],
        "VECTOR6D",
    ),
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    **dict.fromkeys(
        [
            "speed_scaling",
            "target_speed_fraction",
            "actual_momentum",
            "actual_main_voltage",
            "actual_robot_voltage",
            "actual_robot_current",
        ],
        "DOUBLE",
    ),
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "joint_position_deviation_ratio": "DOUBLE",
}
CYCLE = 0.002


@contextlib.contextmanager
def twin(host: str) -> Iterator[URTwin]:
    ref = resources.files("cellcal") / "data" / "mock-cell-ur10e.toml"
    with resources.as_file(ref) as path:
        config = load_config(path, relative_paths=False)
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed=1)
    sim = twin_for_cell(cell, config.robot.home_deg, time_scale=0.0)
    sim.start(host)
    try:
        yield sim
    finally:
        sim.stop()


def recipe_file(outputs: dict[str, str], path: Path) -> Path:
    """An RTDE recipe file in the client's XML format (one "out" recipe)."""
    fields = "".join(f'<field name="{n}" type="{t}"/>' for n, t in outputs.items())
    path.write_text(
        f'<?xml version="1.0"?><rtde_config><recipe key="out">{fields}</recipe></rtde_config>'
    )
    return path


def record(
    host: str, frequency: int, samples: int, config: Path, out: Path
) -> list[dict[str, str]]:
    """Record ``samples`` packages into a CSV file with UR's client and read it back: its
    examples/record.py as its README says (from examples/) where the checkout has it,
    else the same steps on its RTDE class and CSV writer."""
    if HAS_EXAMPLES:
        cmd = [sys.executable, "record.py", "--host", host, "--frequency", str(frequency)]
        cmd += ["--samples", str(samples), "--config", str(config), "--output", str(out)]
        res = subprocess.run(cmd, cwd=EXAMPLES, capture_output=True, text=True, timeout=90)
        assert res.returncode == 0, res.stderr
        assert "Complete!" in res.stdout, (res.stdout, res.stderr)
    else:
        names, types = ur_config.ConfigFile(str(config)).get_recipe("out")
        with connected(host) as con, out.open("w") as f:
            con.get_controller_version()
            assert con.send_output_setup(names, types, frequency=frequency)
            assert con.send_start()
            writer = ur_csv.CSVWriter(f, names, types)
            writer.writeheader()
            written, deadline = 0, time.monotonic() + 60
            while written < samples and time.monotonic() < deadline:
                state = con.receive_buffered()  # None when nothing has come yet
                if state is not None:
                    writer.writerow(state)
                    written += 1
            con.send_pause()
    with out.open() as f:
        return list(csv.DictReader(f, delimiter=" "))


def cycle_steps(rows: list[dict[str, str]]) -> set[int]:
    k = [float(r["timestamp"]) / CYCLE for r in rows]
    assert all(abs(x - round(x)) < 1e-6 for x in k)
    return {round(b - a) for a, b in itertools.pairwise(k)}


@pytest.mark.parametrize(("frequency", "samples"), [(500, 1000), (125, 250), (10, 20)])
def test_record_example_records_at_the_frequency_asked(
    tmp_path: Path, frequency: int, samples: int
) -> None:
    host = {500: "127.0.0.60", 125: "127.0.0.61", 10: "127.0.0.62"}[frequency]
    with twin(host):
        t0 = time.monotonic()
        config = (
            EXAMPLES / "record_configuration.xml"
            if HAS_EXAMPLES
            else recipe_file(RECORD_OUTPUTS, tmp_path / "record.xml")
        )
        rows = record(host, frequency, samples, config, tmp_path / "a.csv")
        elapsed = time.monotonic() - t0
    # record.py counts a sample it did not get when its last read finds nothing yet.
    assert samples - 1 <= len(rows) <= samples
    assert cycle_steps(rows) == {500 // frequency}
    assert elapsed > 0.8 * (samples - 1) / frequency  # paced by the twin, not a burst
    assert float(rows[0]["runtime_state"]) == 1 and int(rows[0]["robot_mode"]) == 7


def test_record_every_output(tmp_path: Path) -> None:
    """UR's record_configuration.xml with its commented-out block of outputs enabled
    (where the checkout has it), else every output the twin serves: all of them through
    the client's own unpacking and CSV writer."""
    if HAS_EXAMPLES:
        text = (EXAMPLES / "record_configuration.xml").read_text()
        out_start = text.index('<recipe key="out">')
        opening = text.index("<!--", out_start)
        closing = text.index("-->", opening)
        full = text[:opening] + text[opening + 4 : closing] + text[closing + 3 :]
        config = tmp_path / "record_all.xml"
        config.write_text(full)
    else:
        served = {n: t for n, t in OUTPUT_TYPES.items() if n not in LATER_OUTPUTS}
        config = recipe_file(served, tmp_path / "record_all.xml")
    names, _types = ur_config.ConfigFile(str(config)).get_recipe("out")
    assert len(names) > 380 and "tcp_offset" in names and "encoder1_raw" in names
    host = "127.0.0.63"
    with twin(host):
        rows = record(host, 125, 100, config, tmp_path / "all.csv")
    assert 99 <= len(rows) <= 100
    assert cycle_steps(rows) == {4}
    assert rows[-1]["payload"] is not None and float(rows[-1]["tool_temperature"]) > 0


@contextlib.contextmanager
def connected(host: str) -> Iterator[Any]:
    con = ur_rtde_client.RTDE(host, 30004)
    con.connect()
    try:
        yield con
    finally:
        con.disconnect()


@pytest.mark.parametrize("frequency", [0, -10, 501, 1000, math.nan])
def test_an_invalid_frequency_fails_the_setup(frequency: float) -> None:
    host = "127.0.0.64"
    with twin(host), connected(host) as con:
        assert con.get_controller_version() == (5, 11, 1, 108318)
        with pytest.raises(ValueError, match="Unknown data type"):
            con.send_output_setup(["timestamp"], ["DOUBLE"], frequency=frequency)
        assert not con.send_start()


def test_an_unknown_or_later_field_fails_the_setup() -> None:
    host = "127.0.0.65"
    with twin(host), connected(host) as con:
        with pytest.raises(ValueError, match="NOT_FOUND"):
            con.send_output_setup(["timestamp", "actual_current_as_torque"], frequency=125)
        assert con.send_output_setup(["timestamp", "tcp_offset"], ["DOUBLE", "VECTOR6D"], 125)


def test_inputs_written_by_the_client_come_back() -> None:
    host = "127.0.0.66"
    with twin(host), connected(host) as con:
        inp = con.send_input_setup(["input_int_register_7", "input_double_register_7"])
        assert inp is not None
        names = ["timestamp", "input_int_register_7", "input_double_register_7"]
        assert con.send_output_setup(names, ["DOUBLE", "INT32", "DOUBLE"], frequency=250)
        assert con.send_start()
        inp.input_int_register_7 = 1234
        inp.input_double_register_7 = -0.5
        con.send(inp)
        deadline = time.monotonic() + 5
        state = con.receive()
        while state.input_int_register_7 != 1234:
            assert time.monotonic() < deadline
            state = con.receive()
        assert state.input_double_register_7 == -0.5
        t0 = con.receive().timestamp
        before = con.skipped_package_count
        t1 = con.receive().timestamp
        # 250 Hz: two cycles a package; the client keeps only the newest of those it
        # finds waiting (a slow reader), and counts the ones it passed over
        assert round((t1 - t0) / CYCLE) == 2 * (1 + con.skipped_package_count - before)
        assert con.send_pause()
