"""Maps with holes: a controller has the registers of its map and no other, and answers a
read that covers a hole with exception 2 (ILLEGAL DATA ADDRESS). The driver reads the
status registers in runs of consecutive addresses, never across a hole, and runs the
handshake on such maps against the twin over real TCP on 127.0.0.x; the twin refuses
what a controller would (the old single read from the lowest to the highest status
register included)."""

from __future__ import annotations

import itertools
import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from cellcal.drivers.modbus_map import ModbusMap
from cellcal.drivers.modbus_robot import ModbusRobot
from cellcal.mocks.modbus.server import ModbusRobotTwin

pytestmark = [pytest.mark.twin, pytest.mark.timeout(30)]

Q0_DEG = [0.0, -90.0, 90.0, 0.0, 45.0, 0.0]
TARGETS_DEG = [
    [10.0, -80.0, 75.5, 20.0, 30.0, -45.0],
    [-5.0, -95.0, 100.0, -10.0, 60.0, 15.0],
    Q0_DEG,
]
_hosts = itertools.cycle(range(151, 171))

#: name: (map, the status poll's reads in order, (first, count) each)
HOLED = {
    # the map: heartbeat 4, status 7; error code and ack at 2 and 3
    "status-apart": (ModbusMap(status=7, heartbeat=4), [(2, 3), (7, 1)]),
    "all-four-apart": (
        ModbusMap(heartbeat=500, status=5, error_code=44, ack=8),
        [(8, 1), (500, 1), (5, 1), (44, 1)],
    ),
    # status registers next to the joints (never merged with them), holes everywhere,
    # little-endian words and another device id
    "holes-everywhere": (
        ModbusMap(
            device_id=9,
            word_order="little",
            heartbeat=9,
            actual_joints=10,
            status=22,
            error_code=23,
            ack=29,
            actual_pose=60,
            target_joints=1000,
            target_pose=1020,
            speed=1100,
            command=2000,
            sequence=2001,
        ),
        [(29, 1), (9, 1), (22, 2)],
    ),
}


def wait_listening(host: str, port: int, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host, port), timeout=0.5).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.005)


@pytest.fixture
def twin(request: pytest.FixtureRequest) -> Iterator[ModbusRobotTwin]:
    sim = ModbusRobotTwin(q0_deg=Q0_DEG, map=request.param, time_scale=0.002)
    host, port = sim.start(f"127.0.0.{next(_hosts)}", 0)
    try:
        wait_listening(host, port)
        yield sim
    finally:
        sim.stop()


def test_status_reads_are_runs_of_consecutive_registers():
    assert ModbusMap().status_reads() == ((0, 4),)
    # one run whatever the order of the four inside it
    assert ModbusMap(heartbeat=3, status=2, error_code=1, ack=0).status_reads() == ((0, 4),)
    for holed, reads in HOLED.values():
        assert list(holed.status_reads()) == reads
    # the status block may now spread wider than one read request
    assert ModbusMap(ack=500).status_reads() == ((500, 1), (0, 3))


@pytest.mark.parametrize(
    ("twin", "reads"),
    [pytest.param(m, r, id=name) for name, (m, r) in HOLED.items()],
    indirect=["twin"],
)
def test_a_map_with_holes_connects_and_moves(twin, reads):
    m = twin.map
    host, port = twin.address
    # The twin refuses a read from the lowest status register to the highest (at most
    # 125 registers: one request).
    lo = min(m.heartbeat, m.status, m.error_code, m.ack)
    hi = max(m.heartbeat, m.status, m.error_code, m.ack)
    raw = ModbusTcpClient(host, port=port, timeout=2.0, retries=0)
    try:
        assert raw.connect()
        count = min(hi - lo + 1, 125)
        rr = raw.read_holding_registers(lo, count=count, device_id=m.device_id)
        assert rr.isError() and rr.exception_code == 2
    finally:
        raw.close()
    twin.clear_requests()

    robot = ModbusRobot(host, port, map=m, timeout_s=10.0, heartbeat_timeout_s=2.0, poll_s=0.002)
    try:
        robot.connect()
        np.testing.assert_allclose(np.degrees(robot.actual_joints()), Q0_DEG, atol=1e-4)
        for target in TARGETS_DEG:
            robot.move_joints(np.radians(target), 0.5)
            np.testing.assert_allclose(twin.q_deg, target, atol=1e-4)
            np.testing.assert_allclose(np.degrees(robot.actual_joints()), target, atol=1e-4)
        assert robot.status().ack == 3
    finally:
        robot.close()

    served = twin.requests
    read = [(r.address, r.count) for r in served if r.values is None]
    assert set(read) == {*reads, (m.actual_joints, 12)}
    # every poll reads the runs in the same order, the one holding ack first
    polls = [x for x in read if x in reads]
    assert polls and polls == reads * (len(polls) // len(reads)), polls[:8]
    written = [(r.address, r.count) for r in served if r.values is not None]
    assert written == [(m.target_joints, 12), (m.speed, 2), (m.command, 2)] * len(TARGETS_DEG)
