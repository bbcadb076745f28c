"""The Modbus TCP robot driver against the Modbus twin over real TCP on
127.0.0.x: the handshake on the wire (one request for command + sequence, exact
registers in both word orders), waiting past "busy clear but not started", every fault
(no acknowledgement, error bit, e-stop, stale heartbeat, local mode), limits, a stop
from elsewhere, a word-order mismatch, exception responses and a vanished server.
A few raw-client checks pin the mock's own register semantics."""

from __future__ import annotations

import itertools
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from cellcal.drivers.modbus_map import BUSY, IN_POSITION
from cellcal.drivers.modbus_robot import ModbusMap, ModbusRobot
from cellcal.errors import DeviceError, InputError
from cellcal.mocks.modbus.server import (
    ModbusRequest,
    ModbusRobotFaults,
    ModbusRobotTwin,
)
from tests.robot_controllers import LIMITS_DEG

pytestmark = [pytest.mark.twin, pytest.mark.timeout(30)]

Q0_DEG = [0.0, -90.0, 90.0, 0.0, 45.0, 0.0]
TARGET_DEG = [10.0, -80.0, 75.5, 20.0, 30.0, -45.0]
_hosts = itertools.cycle(range(61, 100))


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


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.002)


class Bench:
    """Twins and drivers of one test, each twin on its own 127.0.0.x."""

    def __init__(self) -> None:
        self.sims: list[ModbusRobotTwin] = []
        self.robots: list[ModbusRobot] = []
        self.clients: list[ModbusTcpClient] = []

    def sim(self, **kw: object) -> ModbusRobotTwin:
        kw.setdefault("q0_deg", Q0_DEG)
        sim = ModbusRobotTwin(**kw)  # type: ignore[arg-type]
        self.sims.append(sim)
        host, port = sim.start(f"127.0.0.{next(_hosts)}", 0)
        assert port != 0
        wait_listening(host, port)
        return sim

    def robot(self, sim: ModbusRobotTwin, **kw: object) -> ModbusRobot:
        kw.setdefault("timeout_s", 5.0)
        kw.setdefault("heartbeat_timeout_s", 1.0)
        kw.setdefault("poll_s", 0.002)
        host, port = sim.address
        robot = ModbusRobot(host, port, **kw)  # type: ignore[arg-type]
        self.robots.append(robot)
        return robot

    def client(self, sim: ModbusRobotTwin) -> ModbusTcpClient:
        host, port = sim.address
        client = ModbusTcpClient(host, port=port, timeout=2.0, retries=0)
        assert client.connect()
        self.clients.append(client)
        return client

    def close(self) -> None:
        for robot in self.robots:
            robot.close()
        for client in self.clients:
            client.close()
        for sim in self.sims:
            sim.stop()


@pytest.fixture
def bench() -> Iterator[Bench]:
    b = Bench()
    try:
        yield b
    finally:
        b.close()


def f32(values: list[float], word_order: str) -> list[int]:
    """float32 → registers, written out by hand (no pymodbus converters)."""
    out: list[int] = []
    for v in values:
        hi, lo = struct.unpack(">HH", struct.pack(">f", v))
        out += [hi, lo] if word_order == "big" else [lo, hi]
    return out


def writes(requests: list[ModbusRequest]) -> list[ModbusRequest]:
    return [r for r in requests if r.values is not None]


def status_reads(requests: list[ModbusRequest]) -> list[ModbusRequest]:
    """The reads of the status register after the (first) command write."""
    first = next(i for i, r in enumerate(requests) if r.values is not None and r.address == 130)
    return [r for r in requests[first:] if r.status is not None]


# ---------------------------------------------------------------------------- moves


@pytest.mark.parametrize("word_order", ["big", "little"])
def test_move_round_trip_and_exact_registers(bench, word_order):
    """Target joints, speed, then command 1 + sequence in ONE write of 130-131; the
    float32 registers are exactly those of the chosen word order."""
    seen: list[np.ndarray] = []
    sim = bench.sim(
        map=ModbusMap(word_order=word_order, device_id=7),
        limits_deg=LIMITS_DEG,
        on_move=seen.append,
        pose_fn=lambda q: np.array([1000.0, -250.5, 875.25, *np.degrees(q[:3])]),
    )
    robot = bench.robot(sim, map=ModbusMap(word_order=word_order, device_id=7))
    robot.connect()
    np.testing.assert_allclose(np.degrees(robot.actual_joints()), Q0_DEG, atol=1e-4)
    sim.clear_requests()

    robot.move_joints(np.radians(TARGET_DEG), 0.5)

    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)
    np.testing.assert_allclose(robot.actual_joints(), np.radians(TARGET_DEG), atol=1e-6)
    np.testing.assert_allclose(seen[-1], np.radians(TARGET_DEG), atol=1e-6)
    pose = robot.actual_pose()
    np.testing.assert_allclose(pose[:3], [1000.0, -250.5, 875.25], atol=1e-3)
    np.testing.assert_allclose(pose[3:], np.radians(TARGET_DEG[:3]), atol=1e-6)

    w = writes(sim.requests)
    assert [(r.function_code, r.address, r.count) for r in w] == [
        (16, 100, 12),
        (16, 124, 2),
        (16, 130, 2),
    ]
    assert list(w[0].values or ()) == f32(TARGET_DEG, word_order)
    assert list(w[1].values or ()) == f32([0.5], word_order)
    command, seq = w[2].values or (0, 0)
    assert command == 1 and seq == 1
    # nothing wrote 130 or 131 on its own
    assert all(r.address not in (130, 131) or r.count == 2 for r in w)


def test_in_position_follows_the_arrival_not_the_reads(bench):
    """time_scale 0: the robot arrives at once, so the first read after the command sees
    it in position; with time, busy until it arrives however often it is read."""
    sim = bench.sim()
    robot = bench.robot(sim)
    robot.connect()
    sim.clear_requests()
    robot.move_joints(np.radians(TARGET_DEG), 1.0)
    reads = status_reads(sim.requests)
    assert reads[0].ack == 1 and (reads[0].status or 0) & IN_POSITION
    assert not (reads[0].status or 0) & BUSY and len(reads) == 1
    # 30 deg at 60 deg/s: 0.5 s of robot time, 0.15 s of wall time; nobody reads meanwhile.
    slow = bench.sim(q0_deg=[0.0] * 6, time_scale=0.3)
    c = bench.client(slow)
    c.write_registers(100, f32([30.0, 0, 0, 0, 0, 0], "big"), device_id=1)
    c.write_registers(124, f32([1.0], "big"), device_id=1)
    c.write_registers(130, [1, 1], device_id=1)
    assert c.read_holding_registers(1, count=1, device_id=1).registers[0] & BUSY
    time.sleep(0.3)
    status = c.read_holding_registers(1, count=1, device_id=1).registers[0]
    assert status & IN_POSITION and not status & BUSY


def test_busy_clear_before_start_is_not_done(bench):
    """Accepted but not started: ack == seq and busy clear, yet not in position; a driver
    that trusted busy == 0 would return here, at the old joints."""
    sim = bench.sim(faults=ModbusRobotFaults(start_delay_reads=4))
    robot = bench.robot(sim)
    robot.connect()
    sim.clear_requests()
    robot.move_joints(np.radians(TARGET_DEG), 1.0)
    reads = status_reads(sim.requests)
    flags = [
        (r.ack, bool((r.status or 0) & BUSY), bool((r.status or 0) & IN_POSITION)) for r in reads
    ]
    assert flags[:4] == [(1, False, False)] * 4  # the trap: acknowledged, busy clear
    assert flags[4] == (1, False, True)  # started at the 5th read; time_scale 0: arrived
    assert flags[-1] == (1, False, True)
    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)


def test_motion_takes_wall_time_with_time_scale(bench):
    # 30 deg at 60 deg/s × speed 0.5 → 1 s of robot time, × 0.2 → 0.2 s of wall time
    sim = bench.sim(q0_deg=[0.0] * 6, time_scale=0.2)
    robot = bench.robot(sim)
    robot.connect()
    t0 = time.monotonic()
    robot.move_joints(np.radians([30.0, 0, 0, 0, 0, 0]), 0.5)
    assert 0.18 < time.monotonic() - t0 < 2.0
    assert any((r.status or 0) & BUSY for r in status_reads(sim.requests))


def test_consecutive_moves_and_restarted_driver_use_new_sequence_numbers(bench):
    sim = bench.sim()
    robot = bench.robot(sim)
    robot.connect()
    robot.move_joints(np.radians(TARGET_DEG), 1.0)
    robot.move_joints(np.radians(Q0_DEG), 1.0)
    robot.close()
    again = bench.robot(sim)  # a new driver must not reuse the acknowledged number
    again.connect()
    again.move_joints(np.radians(TARGET_DEG), 1.0)
    seqs = [r.values[1] for r in writes(sim.requests) if r.address == 130 and r.values]
    assert seqs == [1, 2, 3]
    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)


# ---------------------------------------------------------------------------- faults


def test_no_acknowledgement_times_out(bench):
    sim = bench.sim(faults=ModbusRobotFaults(no_ack=True))
    robot = bench.robot(sim, timeout_s=0.3)
    robot.connect()
    host, port = sim.address
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=r"not done after 0\.3 s") as err:
        robot.move_joints(np.radians(TARGET_DEG), 1.0)
    assert time.monotonic() - t0 < 3.0
    message = str(err.value)
    assert f"{host}:{port}" in message and "\n" not in message
    # the controller stood still and still claims "in position" with the old ack
    np.testing.assert_allclose(sim.q_deg, Q0_DEG)


def test_error_bit_ends_the_wait_and_names_the_code(bench):
    sim = bench.sim(faults=ModbusRobotFaults(error_code=17))
    robot = bench.robot(sim, timeout_s=20.0)
    robot.connect()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="error code 17"):
        robot.move_joints(np.radians(TARGET_DEG), 1.0)
    assert time.monotonic() - t0 < 2.0
    # a second driver refuses to connect while the error stands; a reset clears it
    other = bench.robot(sim)
    with pytest.raises(DeviceError, match=r"connect refused.*error code 17"):
        other.connect()
    sim.faults = ModbusRobotFaults()
    robot.reset_error()
    other.connect()
    other.move_joints(np.radians(TARGET_DEG), 1.0)


def test_estop_ends_the_wait_and_refuses_connect(bench):
    sim = bench.sim(faults=ModbusRobotFaults(estop=True))
    robot = bench.robot(sim)
    robot.connect()
    with pytest.raises(DeviceError, match="e-stop"):
        robot.move_joints(np.radians(TARGET_DEG), 1.0)
    with pytest.raises(DeviceError, match="e-stop"):
        robot.move_joints(np.radians(TARGET_DEG), 1.0)  # refused before commanding
    with pytest.raises(DeviceError, match="connect refused: e-stop"):
        bench.robot(sim).connect()
    sim.faults = ModbusRobotFaults()
    robot.reset_error()
    robot.move_joints(np.radians(TARGET_DEG), 1.0)


def test_a_protective_stop_every_nth_move(bench):
    """The soak's fault: every 3rd move command ends in a protective stop (e-stop bit);
    a reset clears it and the count goes on."""
    sim = bench.sim(faults=ModbusRobotFaults(estop_every=3))
    robot = bench.robot(sim)
    robot.connect()
    outcomes = []
    for k in range(7):
        target = np.radians(TARGET_DEG) * (1.0 if k % 2 == 0 else 0.5)
        try:
            robot.move_joints(target, 1.0)
            outcomes.append("moved")
        except DeviceError as exc:
            assert "e-stop" in str(exc)
            outcomes.append("stopped")
            robot.reset_error()
    assert outcomes == ["moved", "moved", "stopped", "moved", "moved", "stopped", "moved"]


def test_stale_heartbeat_is_a_comms_fault(bench):
    # a 60 deg move at 60 deg/s lasts 1 s of wall time; the heartbeat gives up at 0.4 s
    sim = bench.sim(
        q0_deg=[0.0] * 6, time_scale=1.0, faults=ModbusRobotFaults(stale_heartbeat=True)
    )
    robot = bench.robot(sim, heartbeat_timeout_s=0.4, timeout_s=20.0)
    robot.connect()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="heartbeat stuck"):
        robot.move_joints(np.radians([60.0, 0, 0, 0, 0, 0]), 1.0)
    assert time.monotonic() - t0 < 0.9
    # the driver sent a stop on its way out: the robot halted short of the target
    assert any(r.address == 130 and r.values and r.values[0] == 3 for r in writes(sim.requests))
    assert sim.q_deg[0] < 60.0


def test_local_mode_refuses(bench):
    sim = bench.sim(faults=ModbusRobotFaults(local=True))
    with pytest.raises(DeviceError, match="not in remote mode"):
        bench.robot(sim).connect()


def test_target_outside_limits_sets_error_code_2(bench):
    sim = bench.sim(limits_deg=LIMITS_DEG)
    robot = bench.robot(sim)
    robot.connect()
    beyond = list(TARGET_DEG)
    beyond[1] = 70.0  # A2 upper limit 65
    with pytest.raises(DeviceError, match="error code 2"):
        robot.move_joints(np.radians(beyond), 1.0)
    np.testing.assert_allclose(sim.q_deg, Q0_DEG)
    robot.reset_error()
    robot.move_joints(np.radians(TARGET_DEG), 1.0)
    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)


def test_stop_from_elsewhere_interrupts_the_move(bench):
    sim = bench.sim(q0_deg=[0.0] * 6, time_scale=1.0)  # 120 deg at 60 deg/s: 2 s
    mover = bench.robot(sim, timeout_s=20.0)
    mover.connect()
    failure: list[BaseException] = []

    def move() -> None:
        try:
            mover.move_joints(np.radians([120.0, 0, 0, 0, 0, 0]), 1.0)
        except BaseException as exc:
            failure.append(exc)

    thread = threading.Thread(target=move)
    thread.start()
    wait_until(lambda: sim.q_deg[0] > 1.0)
    stopper = bench.robot(sim)
    stopper.stop()
    thread.join(10.0)
    assert not thread.is_alive()
    assert len(failure) == 1 and isinstance(failure[0], DeviceError)
    assert "interrupted" in str(failure[0])
    halted = sim.q_deg[0]
    assert 1.0 < halted < 120.0
    status = stopper.status()
    assert not status.busy and not status.in_position
    assert sim.q_deg[0] == halted


@pytest.mark.parametrize(("device", "driver"), [("big", "little"), ("little", "big")])
def test_word_order_mismatch_gives_absurd_joints_that_are_refused(bench, device, driver):
    sim = bench.sim(map=ModbusMap(word_order=device), limits_deg=LIMITS_DEG)
    robot = bench.robot(sim, map=ModbusMap(word_order=driver))
    with pytest.raises(DeviceError, match=r"implausible actual joints.*word order"):
        robot.connect()
    with pytest.raises(DeviceError, match="implausible actual joints"):
        robot.actual_joints()
    with pytest.raises(DeviceError):
        robot.move_joints(np.radians(TARGET_DEG), 0.5)
    np.testing.assert_allclose(sim.q_deg, Q0_DEG)


# ---------------------------------------------------------------------------- errors


def test_exception_responses_become_one_line_device_errors(bench):
    sim = bench.sim()
    host, port = sim.address
    bad_map = bench.robot(sim, map=ModbusMap(actual_joints=50))
    with pytest.raises(DeviceError) as err:
        bad_map.actual_joints()
    message = str(err.value)
    assert f"{host}:{port}" in message and "exception code 2 (ILLEGAL_ADDRESS)" in message
    assert "\n" not in message
    other_id = bench.robot(sim, map=ModbusMap(device_id=9))
    with pytest.raises(DeviceError, match="exception code 11"):
        other_id.connect()


def test_unreachable_and_vanished_server(bench):
    sim = bench.sim()
    robot = bench.robot(sim)
    robot.connect()
    host, port = sim.address
    sim.stop()
    with pytest.raises(DeviceError) as err:
        robot.actual_joints()
    assert f"{host}:{port}" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(DeviceError, match=f"{host}:{port}: cannot connect"):
        ModbusRobot(host, port, heartbeat_timeout_s=1.0).connect()


def test_silent_device_times_out_per_request():
    """A peer that accepts the connection and never answers (a listening socket nobody
    reads): one request waits heartbeat_timeout_s, once (no retries), then DeviceError."""
    with socket.socket() as listener:
        listener.bind((f"127.0.0.{next(_hosts)}", 0))
        listener.listen(4)
        host, port = listener.getsockname()
        robot = ModbusRobot(host, port, heartbeat_timeout_s=0.3)
        try:
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match=f"{host}:{port}: reading status") as err:
                robot.connect()
            assert 0.25 < time.monotonic() - t0 < 2.0
            assert "\n" not in str(err.value)
        finally:
            robot.close()


def test_bad_arguments_are_input_errors(bench):
    sim = bench.sim()
    robot = bench.robot(sim)
    with pytest.raises(InputError):
        robot.move_joints(np.zeros(5), 0.5)
    with pytest.raises(InputError):
        robot.move_joints(np.array([0, 0, np.nan, 0, 0, 0]), 0.5)
    for speed in (0.0, 1.5, float("nan")):
        with pytest.raises(InputError):
            robot.move_joints(np.zeros(6), speed)
    with pytest.raises(ValueError, match="register after command"):
        ModbusMap(command=130, sequence=140)
    with pytest.raises(ValueError, match="word_order"):
        ModbusMap(word_order="middle")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"actual_joints \(registers 10..21\) and actual_pose"):
        ModbusMap(actual_pose=20)
    assert sim.requests == []  # nothing reached the wire


# ---------------------------------------------------------------------------- the mock


def test_mock_register_semantics(bench):
    sim = bench.sim()
    c = bench.client(sim)
    # The heartbeat counts 10 ms cycles: it moves with time, not with the reads.
    t0 = time.monotonic()
    hb0 = c.read_holding_registers(0, count=4, device_id=1).registers[0]
    time.sleep(0.1)
    hb1 = c.read_holding_registers(0, count=4, device_id=1).registers[0]
    elapsed = time.monotonic() - t0
    assert 0.1 / 0.01 - 2 <= (hb1 - hb0) % 65536 <= elapsed / 0.01 + 2
    for address in (4, 22, 42, 126, 132, 1000):  # outside every block
        rr = c.read_holding_registers(address, count=1, device_id=1)
        assert rr.isError() and rr.exception_code == 2
    rr = c.write_registers(10, [0, 0], device_id=1)  # read-only block
    assert rr.isError() and rr.exception_code == 2
    rr = c.read_coils(0, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 1
    # 130 and 131 written one at a time: stored, but no command
    c.write_registers(100, f32(TARGET_DEG, "big"), device_id=1)
    c.write_registers(124, f32([1.0], "big"), device_id=1)
    c.write_register(130, 1, device_id=1)
    c.write_register(131, 5, device_id=1)
    assert c.read_holding_registers(0, count=4, device_id=1).registers[3] == 0
    # together: accepted; the same sequence again is ignored
    c.write_registers(130, [1, 5], device_id=1)
    for _ in range(3):
        regs = c.read_holding_registers(0, count=4, device_id=1).registers
    assert regs[3] == 5 and regs[1] & IN_POSITION
    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)
    c.write_registers(100, f32(Q0_DEG, "big"), device_id=1)
    c.write_registers(130, [1, 5], device_id=1)
    for _ in range(3):
        c.read_holding_registers(0, count=4, device_id=1)
    np.testing.assert_allclose(sim.q_deg, TARGET_DEG, atol=1e-4)
    # move linear is not supported: error code 3
    c.write_registers(130, [2, 6], device_id=1)
    regs = c.read_holding_registers(0, count=4, device_id=1).registers
    assert regs[1] & 0x08 and regs[2] == 3 and regs[3] == 6
