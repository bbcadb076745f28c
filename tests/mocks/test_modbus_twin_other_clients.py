"""The Modbus twin against clients nobody here wrote: pyModbusTCP (not pymodbus, which
the driver is built on) runs the handshake of docs/robots.md on a moved map,
little-endian words and device id 7, as a PLC programmer would, and reads a map with
holes register by register (unmapped ones are exception 2); and raw sockets pin,
byte for byte, what the twin's MBAP server answers where a Modbus/TCP device must
(docs/robots.md, "What the twin answers on the wire"): exception codes echoing the
function code, pipelined requests, a frame of another protocol id, framing errors."""

from __future__ import annotations

import contextlib
import socket
import struct
import time

import numpy as np
import pytest

from cellcal.drivers.modbus_map import BUSY, IN_POSITION, READY, REMOTE, ModbusMap
from cellcal.mocks.modbus.server import ModbusRobotTwin

modbus_tcp = pytest.importorskip("pyModbusTCP.client")

pytestmark = [pytest.mark.twin, pytest.mark.timeout(30)]

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
    sim = ModbusRobotTwin(q0_deg=Q0, map=MAP, time_scale=0.02)
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


#: The issue's map: heartbeat 4 and status 7 beside error code 2 and ack 3, so 5 and 6
#: are holes; and the holes between the other blocks.
HOLED = ModbusMap(heartbeat=4, status=7)
HOLED_REGISTERS = {2, 3, 4, 7, *range(10, 22), *range(30, 42), *range(100, 126), 130, 131}


def _wait_listening(host, port, timeout=5.0):
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host, port), timeout=0.5).close()
            return
        except OSError:
            assert time.monotonic() < deadline, f"nothing listening on {host}:{port}"
            time.sleep(0.005)


def test_pymodbustcp_reads_the_registers_of_a_map_with_holes():
    """What a controller answers: every mapped register reads, every other address, a
    hole between two blocks included, is exception 2, and so is any range across one
    (the single read 2..7 of the status registers that earlier drivers sent)."""
    sim = ModbusRobotTwin(q0_deg=Q0, map=HOLED)
    host, port = sim.start("127.0.0.96", 0)
    c = modbus_tcp.ModbusClient(host=host, port=port, unit_id=1, timeout=2.0, auto_open=True)
    try:
        _wait_listening(host, port)
        for address in range(140):
            for read in (c.read_holding_registers, c.read_input_registers):
                regs = read(address, 1)
                if address in HOLED_REGISTERS:
                    assert regs is not None and len(regs) == 1, address
                else:
                    assert regs is None and c.last_except == 2, address
        error_code, ack, _ = c.read_holding_registers(2, 3)
        (status,) = c.read_holding_registers(7, 1)
        assert (error_code, ack) == (0, 0) and status & READY and status & REMOTE
        np.testing.assert_allclose(floats(c.read_holding_registers(10, 12), "big"), Q0, atol=1e-5)
        assert len(c.read_holding_registers(100, 26)) == 26  # target joints, pose, speed
        for address, count in ((2, 6), (4, 4), (3, 5), (10, 13), (100, 27), (125, 6)):
            assert c.read_holding_registers(address, count) is None, (address, count)
            assert c.last_except == 2
        assert not c.write_single_register(5, 1) and c.last_except == 2
        assert not c.write_multiple_registers(126, [0, 0]) and c.last_except == 2
    finally:
        c.close()
        sim.stop()
    # nothing refused was served, nothing was written
    assert all(r.values is None for r in sim.requests)
    assert {r.address for r in sim.requests} <= HOLED_REGISTERS


def _mbap(tid, pdu, unit=7, proto=0):
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1, unit) + pdu


def _replies(sock, expected=None, wait=0.05):
    """What the server sends: ``len(expected)`` bytes (2 s at most), then whatever follows
    within ``wait`` seconds (without ``expected``: until ``wait`` seconds of silence)."""
    out = b""
    if expected:
        sock.settimeout(2.0)
        with contextlib.suppress(TimeoutError):
            while len(out) < len(expected) and (chunk := sock.recv(4096)):
                out += chunk
    sock.settimeout(wait)
    with contextlib.suppress(TimeoutError):
        while chunk := sock.recv(4096):
            out += chunk
    return out


def _expect(sock, frames, expected):
    """Send ``frames`` in one segment; the server answers exactly ``expected``."""
    sock.sendall(b"".join(frames))
    got = _replies(sock, expected, wait=0.05 if expected else 0.3)
    assert got.hex() == expected.hex(), b"".join(frames).hex()


def _read(address, count, fc=3):
    return struct.pack(">BHH", fc, address, count)


def _write(address, values):
    return struct.pack(f">BHHB{len(values)}H", 16, address, len(values), 2 * len(values), *values)


def test_exception_replies_echo_the_function_code(twin):
    sim, host, port = twin
    cases = [
        # quantity out of range: illegal data value (3)
        (_read(MAP.status, 0), "8303"),
        (_read(MAP.status, 126), "8303"),
        (_read(MAP.status, 0, fc=4), "8403"),
        (struct.pack(">BHHB", 16, MAP.speed, 0, 0), "9003"),
        (struct.pack(">BHHB", 16, MAP.target_joints, 124, 248), "9003"),  # 124: no frame holds it
        (struct.pack(">BHHB2H", 16, MAP.speed, 2, 3, 0, 0), "9003"),  # byte count 3 for 2
        (struct.pack(">BHHB3H", 16, MAP.speed, 2, 4, 0, 0, 0), "9003"),  # 6 bytes for 4
        (struct.pack(">BHHHHB", 23, MAP.status, 0, MAP.speed, 1, 2) + b"\0\0", "9703"),
        (struct.pack(">BHHHHB", 23, MAP.status, 1, MAP.speed, 0, 0), "9703"),
        (_read(MAP.status, 1)[:3], "8303"),  # a PDU too short
        # function codes not served: illegal function (1), coils and discrete inputs too
        (bytes([0x41, 0, 0]), "c101"),
        (_read(0, 1, fc=1), "8101"),
        (_read(0, 1, fc=2), "8201"),
        (struct.pack(">BHH", 5, 0, 0xFF00), "8501"),
        (struct.pack(">BHHBB", 15, 0, 1, 1, 1), "8f01"),
        # addresses: not mapped, or a write to a read-only register (2)
        (_read(1, 1), "8302"),
        (_read(MAP.ack, 2), "8302"),  # runs past the status block into a gap
        (_read(0xFFFF, 2), "8302"),  # runs past 65535
        (struct.pack(">BHH", 6, MAP.status, 1), "8602"),
        (_write(MAP.actual_joints, [0, 0]), "9002"),
        (struct.pack(">BHHHHB2H", 23, 5, 1, MAP.speed, 2, 4, 0, 0), "9702"),  # bad read
    ]
    with socket.create_connection((host, port), timeout=2.0) as s:
        for tid, (pdu, answer) in enumerate(cases, start=1):
            expected = struct.pack(">HHHB", tid, 0, 3, 7) + bytes.fromhex(answer)
            _expect(s, [_mbap(tid, pdu)], expected)
        # another device id: the gateway's "target failed to respond", whatever the request
        for tid, pdu, answer in ((100, _read(MAP.status, 1), "830b"), (101, b"\x41", "c10b")):
            expected = struct.pack(">HHHB", tid, 0, 3, 3) + bytes.fromhex(answer)
            _expect(s, [_mbap(tid, pdu, unit=3)], expected)
    assert sim.requests == []  # a refused request does nothing, not even 23's write


def test_a_failing_simulated_cell_answers_device_failure():
    def broken(q):
        raise RuntimeError("the simulated cell failed")

    sim = ModbusRobotTwin(q0_deg=Q0, map=MAP, pose_fn=broken)
    host, port = sim.start("127.0.0.95", 0)
    try:
        with socket.create_connection((host, port), timeout=2.0) as s:
            _expect(s, [_mbap(1, _read(MAP.ack, 1))], _mbap(1, bytes.fromhex("8304")))
            _expect(s, [_mbap(2, _read(MAP.ack, 1, fc=4))], _mbap(2, bytes.fromhex("8404")))
            sim.pose_fn = None
            _expect(s, [_mbap(3, _read(MAP.ack, 1))], _mbap(3, bytes.fromhex("03020000")))
    finally:
        sim.stop()


def test_served_function_codes_answer_as_the_spec_says(twin):
    sim, host, port = twin
    with socket.create_connection((host, port), timeout=2.0) as s:
        # 3 and 4 read the same registers: error code 0, ack 0
        _expect(
            s, [_mbap(1, _read(MAP.error_code, 2))], bytes.fromhex("00010000000707030400000000")
        )
        _expect(
            s,
            [_mbap(2, _read(MAP.error_code, 2, fc=4))],
            bytes.fromhex("00020000000707040400000000"),
        )
        # 6 echoes the request, 16 the address and quantity
        single = _mbap(3, struct.pack(">BHH", 6, MAP.command, 0))
        _expect(s, [single], single)
        _expect(
            s,
            [_mbap(4, _write(MAP.speed, [0x3F80, 0]))],
            _mbap(4, struct.pack(">BHH", 16, MAP.speed, 2)),
        )
        # 23 writes command + sequence (a command: acknowledged), then reads the ack
        rw = struct.pack(">BHHHHB2H", 23, MAP.ack, 1, MAP.command, 2, 4, 0, 9)
        _expect(s, [_mbap(5, rw)], _mbap(5, bytes.fromhex("17020009")))
    got = [(r.function_code, r.address, r.count, r.values, r.ack) for r in sim.requests]
    assert got[-2:] == [(23, MAP.command, 2, (0, 9), None), (23, MAP.ack, 1, None, 9)]


def test_pipelined_requests_are_all_answered_in_order(twin):
    _, host, port = twin
    with socket.create_connection((host, port), timeout=2.0) as s:
        _expect(
            s,
            [
                _mbap(3, _read(MAP.ack, 1)),
                _mbap(4, bytes([0x41])),
                _mbap(5, _write(MAP.target_pose, [1, 2])),
                _mbap(6, _read(MAP.target_pose, 2)),  # sees the write before it
                _mbap(7, _read(MAP.error_code, 1)),
            ],
            b"".join(
                [
                    _mbap(3, bytes.fromhex("03020000")),
                    _mbap(4, bytes.fromhex("c101")),
                    _mbap(5, struct.pack(">BHH", 16, MAP.target_pose, 2)),
                    _mbap(6, bytes.fromhex("030400010002")),
                    _mbap(7, bytes.fromhex("03020000")),
                ]
            ),
        )
        # a request split over several segments is answered once whole
        frame = _mbap(8, _read(MAP.ack, 1))
        for i in range(len(frame)):
            s.sendall(frame[i : i + 1])
            time.sleep(0.002)
        expected = _mbap(8, bytes.fromhex("03020000"))
        assert _replies(s, expected) == expected


def test_a_frame_of_another_protocol_id_is_dropped_and_the_next_answered(twin):
    _, host, port = twin
    read = _read(MAP.ack, 1)
    with socket.create_connection((host, port), timeout=2.0) as s:
        _expect(s, [_mbap(5, read, proto=5)], b"")
        _expect(s, [_mbap(6, read)], _mbap(6, bytes.fromhex("03020000")))
        # in one segment: the foreign frame, however long, is skipped
        frames = [_mbap(7, read), _mbap(8, b"\xff" * 40, proto=0x1234), _mbap(9, read)]
        answer = bytes.fromhex("03020000")
        _expect(s, frames, _mbap(7, answer) + _mbap(9, answer))


@pytest.mark.parametrize("length", [0, 1, 255, 0xFFFF])
def test_a_bad_length_field_closes_the_connection(twin, length):
    _, host, port = twin
    read = _read(MAP.ack, 1)
    bad = struct.pack(">HHH", 2, 0, length)
    with socket.create_connection((host, port), timeout=2.0) as s:
        # the frame before it is answered, then the connection closes (EOF or reset)
        s.sendall(_mbap(1, read) + bad)
        s.settimeout(2.0)
        got = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := s.recv(4096):
                got += chunk
        assert got == _mbap(1, bytes.fromhex("03020000"))
    # the server goes on serving other connections
    with socket.create_connection((host, port), timeout=2.0) as s:
        _expect(s, [_mbap(3, read)], _mbap(3, bytes.fromhex("03020000")))


def test_stop_closes_the_open_connections():
    sim = ModbusRobotTwin(q0_deg=Q0, map=MAP)
    host, port = sim.start("127.0.0.94", 0)
    try:
        with socket.create_connection((host, port), timeout=2.0) as s:
            _expect(s, [_mbap(1, _read(MAP.ack, 1))], _mbap(1, bytes.fromhex("03020000")))
            sim.stop()
            s.settimeout(2.0)
            with contextlib.suppress(ConnectionResetError):
                assert s.recv(4096) == b""
        with pytest.raises(OSError):
            socket.create_connection((host, port), timeout=1.0).close()
        sim.stop()  # idempotent
        with pytest.raises(RuntimeError, match="not running"):
            _ = sim.address
    finally:
        sim.stop()
