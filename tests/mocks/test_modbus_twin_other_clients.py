"""The Modbus twin against a client nobody here wrote: pyModbusTCP (not pymodbus, which
both the driver and the twin are built on) runs the handshake of docs/robots.md on a
moved map, little-endian words and device id 7, as a PLC programmer would. And the
pymodbus 3.16 server behaviours the twin inherits, pinned byte for byte: if pymodbus
changes them, this test fails and docs/robots.md must be brought up to date."""

from __future__ import annotations

import contextlib
import socket
import struct
import time

import numpy as np
import pytest

from cellcal.drivers.modbus_map import BUSY, IN_POSITION, READY, REMOTE, ModbusMap
from cellcal.mocks.modbus_robot_server import ModbusRobotSimulator

modbus_tcp = pytest.importorskip("pyModbusTCP.client")

pytestmark = pytest.mark.timeout(30)

MAP = ModbusMap(
    device_id=7,
    word_order="little",
    heartbeat=2000,
    status=2001,
    error_code=2002,
    ack=2003,
    actual_joints=2010,
    actual_pose=2030,
    target_joints=2100,
    target_pose=2112,
    speed=2124,
    command=2130,
    sequence=2131,
)
Q0 = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
TARGET = [12.5, -25.0, 47.25, 8.0, -31.0, 90.0]


def f32(values, order):
    out = []
    for v in values:
        hi, lo = struct.unpack(">HH", struct.pack(">f", v))
        out += [hi, lo] if order == "big" else [lo, hi]
    return out


def floats(regs, order):
    pairs = [regs[i : i + 2] for i in range(0, len(regs), 2)]
    return [
        struct.unpack(">f", struct.pack(">HH", *(p if order == "big" else p[::-1])))[0]
        for p in pairs
    ]


@pytest.fixture
def twin():
    sim = ModbusRobotSimulator(q0_deg=Q0, map=MAP, time_scale=0.02)
    host, port = sim.start("127.0.0.93", 0)
    yield sim, host, port
    sim.stop()


def test_pymodbustcp_runs_the_handshake_on_the_configured_map(twin):
    _, host, port = twin
    c = modbus_tcp.ModbusClient(host=host, port=port, unit_id=7, timeout=2.0, auto_open=True)
    try:
        _, status, code, ack = c.read_holding_registers(MAP.heartbeat, 4)
        assert status & READY and status & REMOTE and status & IN_POSITION and code == 0
        joints = c.read_holding_registers(MAP.actual_joints, 12)
        np.testing.assert_allclose(floats(joints, "little"), Q0, atol=1e-5)
        assert c.write_multiple_registers(MAP.target_joints, f32(TARGET, "little"))
        assert c.write_multiple_registers(MAP.speed, f32([0.5], "little"))
        seq = ack % 0xFFFF + 1
        assert c.write_multiple_registers(MAP.command, [1, seq])
        deadline = time.monotonic() + 10.0
        while True:
            _, status, code, ack = c.read_holding_registers(MAP.heartbeat, 4)
            if ack == seq and status & IN_POSITION and not status & BUSY:
                break
            assert code == 0 and time.monotonic() < deadline
            time.sleep(0.005)
        np.testing.assert_allclose(
            floats(c.read_holding_registers(MAP.actual_joints, 12), "little"), TARGET, atol=1e-4
        )
        # The default map's addresses are not this device's.
        assert c.read_holding_registers(1, 1) is None and c.last_except == 2
        # Another device id: the gateway's "target failed to respond".
        c.unit_id = 3
        assert c.read_holding_registers(MAP.status, 1) is None and c.last_except == 0x0B
    finally:
        c.close()


def _mbap(tid, pdu, unit=7, proto=0):
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1, unit) + pdu


def _replies(sock, wait=0.4):
    """Everything the server sends until it has been silent for ``wait`` seconds."""
    sock.settimeout(wait)
    out = b""
    with contextlib.suppress(TimeoutError):
        while chunk := sock.recv(4096):
            out += chunk
    return out


def test_pymodbus_server_behaviours_the_twin_inherits(twin):
    """Documented in docs/robots.md ("What the twin inherits from pymodbus")."""
    _, host, port = twin
    read = struct.pack(">BHH", 3, MAP.status, 1)
    with socket.create_connection((host, port), timeout=2.0) as s:
        # A read of 0 registers (illegal data value, 0x83 03, on a real device) and an
        # unknown function code (0xC1 01) both answer function code 0x80, exception 1.
        s.sendall(_mbap(1, struct.pack(">BHH", 3, MAP.status, 0)))
        assert _replies(s) == bytes.fromhex("000100000003078001")
        s.sendall(_mbap(2, bytes([0x41, 0, 0])))
        assert _replies(s) == bytes.fromhex("000200000003078001")
        # Two requests in one segment: only the first is answered.
        s.sendall(_mbap(3, read) + _mbap(4, read))
        got = _replies(s)
        assert got[:2] == b"\x00\x03" and b"\x00\x04\x00\x00" not in got
    with socket.create_connection((host, port), timeout=2.0) as s:
        # A frame with protocol id 5 is dropped, and so is every request after it on
        # that connection; a new connection is served again.
        s.sendall(_mbap(5, read, proto=5))
        assert _replies(s) == b""
        s.sendall(_mbap(6, read))
        assert _replies(s) == b""
    with socket.create_connection((host, port), timeout=2.0) as s:
        s.sendall(_mbap(7, read))
        assert _replies(s)[:2] == b"\x00\x07"
