"""The UR twin on the wire, struct by struct, with no third-party client: what UR's own
RTDE client (tests/mocks/test_ur_official_client.py, not on PyPI) relies on, pinned here
so that CI guards it (docs/ur-twin.md): the RTDE output frequency and its refusal,
protocol v1 framing, the 5.11 output field table, timestamps counting 2 ms cycles, the
dashboard's answers, and the real-time state stream on 30003.

Every test binds its own loopback address (the ports are fixed)."""

from __future__ import annotations

import contextlib
import itertools
import math
import socket
import struct
import time
from collections.abc import Iterator
from importlib import resources

import numpy as np
import pytest

from cellcal.config import load_config
from cellcal.files.models import load_model
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.ur.fields import OUTPUT_TYPES
from cellcal.mocks.ur.rtde_codec import TYPE_CODES
from cellcal.mocks.ur.server import URTwin, twin_for_cell

pytestmark = [pytest.mark.twin, pytest.mark.timeout(60, method="thread")]

CYCLE = 0.002
VER, OUT, INP, START, PAUSE, DATA, TEXT = (ord(c) for c in "VOISPUM")


def _cell() -> tuple[list[float], SimulatedCell]:
    ref = resources.files("cellcal") / "data" / "mock-cell-ur10e.toml"
    with resources.as_file(ref) as path:
        config = load_config(path, relative_paths=False)
    return list(config.robot.home_deg), SimulatedCell(config, load_model("ur10e").model, seed=1)


HOME_DEG, CELL = _cell()


@contextlib.contextmanager
def twin(host: str) -> Iterator[URTwin]:
    sim = twin_for_cell(CELL, HOME_DEG, time_scale=0.0)
    sim.start(host)
    try:
        yield sim
    finally:
        sim.stop()


class Rtde:
    """A minimal RTDE client: exact header, exact payload."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, 30004), timeout=5)
        self.buf = b""

    def close(self) -> None:
        self.sock.close()

    def send(self, mtype: int, payload: bytes = b"") -> None:
        self.sock.sendall(struct.pack(">HB", len(payload) + 3, mtype) + payload)

    def _exact(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(65536)
            assert chunk, "connection closed"
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self) -> tuple[int, bytes]:
        size, mtype = struct.unpack(">HB", self._exact(3))
        return mtype, self._exact(size - 3)

    def ask(self, mtype: int, payload: bytes = b"") -> bytes:
        self.send(mtype, payload)
        got, body = self.recv()
        assert got == mtype, (got, body)
        return body

    def timestamps(self, n: int, offset: int = 1) -> list[float]:
        """The timestamps of the next n data packages (a recipe of ``timestamp`` only)."""
        out = []
        while len(out) < n:
            mtype, body = self.recv()
            if mtype == DATA:
                out.append(struct.unpack_from(">d", body, offset)[0])
        return out


@contextlib.contextmanager
def rtde(host: str, version: int = 2) -> Iterator[Rtde]:
    c = Rtde(host)
    try:
        assert c.ask(VER, struct.pack(">H", version)) == b"\x01"
        yield c
    finally:
        c.close()


def cycles(ts: list[float]) -> list[int]:
    k = [t / CYCLE for t in ts]
    assert all(abs(x - round(x)) < 1e-6 for x in k), "a timestamp off the 2 ms grid"
    return [round(b - a) for a, b in itertools.pairwise(k)]


# -- RTDE output frequency ------------------------------------------------------------


@pytest.mark.parametrize("frequency", [500.0, 125.0, 50.0, 10.0])
def test_outputs_go_out_at_the_frequency_asked_on_whole_cycles(frequency: float) -> None:
    host = {500.0: "127.0.0.40", 125.0: "127.0.0.41", 50.0: "127.0.0.42", 10.0: "127.0.0.43"}[
        frequency
    ]
    with twin(host), rtde(host) as c:
        assert c.ask(OUT, struct.pack(">d", frequency) + b"timestamp") == b"\x01DOUBLE"
        assert c.ask(START) == b"\x01"
        n = max(5, int(frequency * 0.6))
        t0 = time.monotonic()
        ts = c.timestamps(n)
        elapsed = time.monotonic() - t0
        # Consecutive packages exactly 500/f cycles apart: 1 at 500 Hz, 4 at 125 Hz.
        assert set(cycles(ts)) == {round(500 / frequency)}
        rate = (n - 1) / elapsed
        assert 0.5 * frequency < rate < 1.5 * frequency, rate


def test_a_frequency_that_does_not_divide_500_keeps_its_average() -> None:
    host = "127.0.0.44"
    with twin(host), rtde(host) as c:
        assert c.ask(OUT, struct.pack(">d", 300.0) + b"timestamp")[0] == 1
        assert c.ask(START) == b"\x01"
        steps = cycles(c.timestamps(61))
        assert set(steps) == {1, 2} and sum(steps) == 100  # 60 packages in 100 cycles


@pytest.mark.parametrize("frequency", [0.0, -125.0, 500.5, 1000.0, math.nan, math.inf])
def test_an_invalid_frequency_is_refused(frequency: float) -> None:
    host = "127.0.0.45"
    with twin(host), rtde(host) as c:
        c.send(OUT, struct.pack(">d", frequency) + b"timestamp,actual_q")
        mtype, text = c.recv()
        assert mtype == TEXT  # v2 text message: len, message, len, source, level (error)
        msg = text[1 : 1 + text[0]].decode()
        assert "frequency" in msg and text[-1] == 1
        assert c.recv() == (OUT, b"\x00")  # recipe id 0: refused, no types
        assert c.ask(START) == b"\x00"  # nothing to start


def test_protocol_v1_is_framed_as_v1() -> None:
    host = "127.0.0.46"
    with twin(host), rtde(host, version=1) as c:
        # No frequency in the request, no recipe id in the reply nor in the data.
        assert c.ask(OUT, b"timestamp,actual_q") == b"DOUBLE,VECTOR6D"
        assert c.ask(OUT, b"timestamp") == b"DOUBLE"  # v1 has one output recipe: replaced
        assert c.ask(INP, b"input_int_register_3") == b"\x01INT32"  # input ids stay
        assert c.ask(START) == b"\x01"
        mtype, body = c.recv()
        assert mtype == DATA and len(body) == 8
        assert set(cycles(c.timestamps(20, offset=0))) == {1}  # v1: 500 Hz
        c.send(PAUSE)
        msg = c.recv()
        while msg[0] == DATA:  # data packets already on the way before the pause
            msg = c.recv()
        assert msg == (PAUSE, b"\x01")


def test_version_3_is_refused() -> None:
    host = "127.0.0.47"
    with twin(host):
        c = Rtde(host)
        try:
            assert c.ask(VER, struct.pack(">H", 3)) == b"\x00"
        finally:
            c.close()


# -- the field table ------------------------------------------------------------------

#: Outputs of a 5.11 controller with the guide's types (a sample across the table).
GUIDE = {
    "tcp_offset": "VECTOR6D",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "tool_output_mode": "UINT8",
    "tool_output_voltage": "INT32",
    "standard_analog_input0": "DOUBLE",
    "analog_io_types": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "actual_digital_output_bits": "UINT64",
    "joint_mode": "VECTOR6INT32",
    "output_bit_register_64": "BOOL",
    "input_double_register_47": "DOUBLE",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
}


def test_every_output_of_the_table_is_served_with_its_type() -> None:
    host = "127.0.0.48"
    names = list(OUTPUT_TYPES)
    assert GUIDE.items() <= OUTPUT_TYPES.items()
    with twin(host), rtde(host) as c:
        body = c.ask(OUT, struct.pack(">d", 125.0) + ",".join(names).encode())
        assert body[0] == 1
        assert body[1:].decode().split(",") == [OUTPUT_TYPES[n] for n in names]
        for later in (b"actual_current_as_torque", b"actual_qdd", b"no_such_field"):
            assert c.ask(OUT, struct.pack(">d", 125.0) + b"timestamp," + later) == (
                b"\x00DOUBLE,NOT_FOUND"
            )
        assert c.ask(START) == b"\x01"
        mtype, data = c.recv()
        fmt = ">B" + "".join(TYPE_CODES[OUTPUT_TYPES[n]] for n in names)
        assert mtype == DATA and len(data) == struct.calcsize(fmt)
        values = dict(zip(names, _split(struct.unpack(fmt, data)[1:], names), strict=True))
    q0 = np.radians(HOME_DEG)
    np.testing.assert_allclose(values["actual_q"], q0, atol=1e-12)
    np.testing.assert_allclose(values["target_q"], q0, atol=1e-12)
    pose = values["actual_TCP_pose"]
    np.testing.assert_allclose(np.array(pose[:3]) * 1000, CELL.flange_pose(q0)[:3, 3], atol=1e-9)
    assert values["robot_mode"] == 7 and values["runtime_state"] == 1
    assert values["joint_mode"] == [253] * 6
    assert values["tcp_force_scalar"] == pytest.approx(
        np.linalg.norm(values["actual_TCP_force"][:3])
    )
    assert 40.0 < values["actual_main_voltage"] < 50.0
    assert all(20.0 < t < 60.0 for t in values["joint_temperatures"])
    assert values["target_speed_fraction"] == 1.0 and values["speed_scaling"] == 1.0


def _split(flat: tuple[object, ...], names: list[str]) -> list[object]:
    out: list[object] = []
    i = 0
    for n in names:
        k = (
            6
            if OUTPUT_TYPES[n].startswith("VECTOR6")
            else 3
            if OUTPUT_TYPES[n] == "VECTOR3D"
            else 1
        )
        out.append(list(flat[i : i + k]) if k > 1 else flat[i])
        i += k
    return out


def test_inputs_come_back_as_outputs_and_drive_the_slider_and_outputs() -> None:
    host = "127.0.0.49"
    with twin(host), rtde(host) as c:
        names = b"input_int_register_5,speed_slider_mask,speed_slider_fraction,"
        names += b"standard_digital_output_mask,standard_digital_output"
        assert c.ask(INP, names) == b"\x01INT32,UINT32,DOUBLE,UINT8,UINT8"
        outs = b"timestamp,input_int_register_5,target_speed_fraction,actual_digital_output_bits"
        assert c.ask(OUT, struct.pack(">d", 500.0) + outs)[0] == 1
        assert c.ask(START) == b"\x01"
        c.send(DATA, struct.pack(">BiIdBB", 1, -42, 1, 0.25, 0b101, 0b100))
        deadline = time.monotonic() + 5
        while True:
            mtype, body = c.recv()
            if mtype == DATA:
                _, _, reg, frac, bits = struct.unpack(">BdidQ", body)
                if reg == -42:
                    break
            assert time.monotonic() < deadline
        assert frac == 0.25 and bits == 0b100


# -- timestamps -------------------------------------------------------------------------


def test_timestamps_are_whole_cycles_on_every_connection() -> None:
    host = "127.0.0.50"
    with twin(host), rtde(host) as a, rtde(host) as b:
        for c, f in ((a, 250.0), (b, 125.0)):
            assert c.ask(OUT, struct.pack(">d", f) + b"timestamp")[0] == 1
            assert c.ask(START) == b"\x01"
        assert set(cycles(a.timestamps(50))) == {2}
        assert set(cycles(b.timestamps(25))) == {4}


# -- dashboard --------------------------------------------------------------------------


def dashboard(host: str, lines: list[str]) -> list[str]:
    with socket.create_connection((host, 29999), timeout=5) as s:
        f = s.makefile("rwb")
        replies = [f.readline().decode().rstrip("\n")]
        for line in lines:
            f.write((line + "\n").encode())
            f.flush()
            replies.append(f.readline().decode().rstrip("\n"))
        return replies


def test_dashboard_programs_and_versions() -> None:
    host = "127.0.0.51"
    script = [
        ("stop", "Failed to execute: stop"),
        ("get loaded program", "No program loaded"),
        ("load nowhere.urp", "File not found: nowhere.urp"),
        ("load default.urp", "Loading program: default.urp"),
        ("get loaded program", "Loaded program: /programs/default.urp"),
        ("isProgramSaved", "true default.urp"),
        ("programState", "STOPPED default.urp"),
        ("play", "Starting program"),
        ("running", "Program running: true"),
        ("programState", "PLAYING default.urp"),
        (
            "load /programs/calibration.urp",
            "Error while loading program: /programs/calibration.urp",
        ),
        ("pause", "Pausing program"),
        ("running", "Program running: false"),
        ("play", "Starting program"),
        ("stop", "Stopped"),
        ("stop", "Failed to execute: stop"),
        ("pause", "Failed to execute: pause"),
        ("version", "5.11.1.108318"),
        ("PolyscopeVersion", "URSoftware 5.11.1.108318 (Mar 22 2021)"),
        ("get robot model", "UR10"),
        ("addToLog calibration started", "Added log message"),
        ("popup hello", "showing popup"),
        ("get operational mode", "NONE"),
        ("frobnicate now", "could not understand: 'frobnicate now'"),
    ]
    with twin(host):
        replies = dashboard(host, [line for line, _ in script])
    assert replies[0] == "Connected: Universal Robots Dashboard Server"
    assert replies[1:] == [answer for _, answer in script]


# -- the real-time interface (30003) ------------------------------------------------------

RT = struct.Struct(">i152d")


def read_realtime(sock: socket.socket, n: int) -> list[tuple[float, ...]]:
    buf = b""
    out = []
    while len(out) < n:
        while len(buf) < RT.size:
            chunk = sock.recv(65536)
            assert chunk, "connection closed"
            buf += chunk
        size = struct.unpack_from(">i", buf)[0]
        assert size == RT.size == 1220
        out.append(RT.unpack_from(buf)[1:])
        buf = buf[RT.size :]
    return out


def test_port_30003_streams_the_state_at_500_hz() -> None:
    host = "127.0.0.52"
    with twin(host), socket.create_connection((host, 30003), timeout=5) as s:
        read_realtime(s, 5)
        t0 = time.monotonic()
        packets = read_realtime(s, 250)
        elapsed = time.monotonic() - t0
    assert 250 < 249 / elapsed < 750
    times = [p[0] for p in packets]
    assert set(cycles(times)) == {1}
    p = packets[-1]
    q0 = np.radians(HOME_DEG)
    np.testing.assert_allclose(p[31:37], q0, atol=1e-12)  # q actual, columns 32-37
    np.testing.assert_allclose(p[1:7], q0, atol=1e-12)  # q target, columns 2-7
    assert p[94] == 7.0 and p[95:101] == (253.0,) * 6 and p[101] == 1.0  # modes, safety


def test_a_30003_client_that_does_not_read_never_blocks_the_controller() -> None:
    host = "127.0.0.53"
    with twin(host):
        lazy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lazy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        lazy.connect((host, 30003))
        try:
            with rtde(host) as c:
                assert c.ask(OUT, struct.pack(">d", 500.0) + b"timestamp")[0] == 1
                assert c.ask(START) == b"\x01"
                t0 = time.monotonic()
                ts = c.timestamps(750)  # 1.5 s of data while nobody reads 30003
                assert time.monotonic() - t0 < 3.0
                assert set(cycles(ts)) == {1}
            assert dashboard(host, ["running"])[1] == "Program running: false"
            lazy.settimeout(5)
            assert len(read_realtime(lazy, 20)) == 20  # whole packets, dropped ones skipped
        finally:
            lazy.close()
