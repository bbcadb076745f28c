"""A protocol-level mock of a robot controller behind Modbus TCP, with the handshake
register map of ``docs/robots.md``, so that the real
:class:`~cellcal.drivers.modbus_robot.ModbusRobot` (or any Modbus client) runs unchanged
against it.

Three modules make the twin: ``mbap.py``, Modbus/TCP framing and the PDU codec;
``mocks/modbus/state.py``, the controller (registers, status, commands, faults, motion;
its docstring is the behaviour contract); this one, the server: MBAP over the project's
:class:`~cellcal.mocks.link_server.TcpLinkServer` (a thread per connection), and
:func:`serve`, the twin of a configured robot.

On the wire it answers as a Modbus/TCP device does (Modbus Application Protocol v1.1b3,
Modbus Messaging on TCP/IP Implementation Guide v1.0b):

* Function codes 3 and 4 (the same registers), 6, 16 and 23. Exception replies carry the
  request's function code + 0x80 and the code: 1 a function code not served (coils and
  discrete inputs included), 3 a quantity out of range or a byte count that does not
  match it, 2 an address not mapped or a write to a read-only register, 4 a failing
  ``on_move`` or ``pose_fn``, 0x0B (gateway target failed to respond) a unit id other
  than the map's device id.
* Requests that arrive together (pipelined, in one segment) are all answered, in order,
  each with its transaction id.
* A frame whose protocol id is not 0 is dropped, unanswered (its length field still
  delimits it); the connection goes on with the next frame.
* A length field below 2 or above 254 is a framing error: the connection is closed
  (after the answers to the frames before it).
* What a connection holds is bounded: an unfinished frame (at most 260 bytes) and the
  answers to one read (64 KiB) of requests; a client that reads none of them for
  ``link_server.WRITE_STALL_S`` is closed, with a log line.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.calib.rotations import euler_zyx_from_matrix
from cellcal.mocks.link_server import POLL_S, Link, TcpLinkServer
from cellcal.mocks.modbus.mbap import (
    GATEWAY_TARGET_FAILED,
    Frame,
    ModbusError,
    decode_request,
    encode_frame,
    exception_pdu,
    floats_to_registers,
    registers_to_floats,
    reply_pdu,
    split_frames,
)
from cellcal.mocks.modbus.state import (
    ModbusRequest,
    ModbusRobotController,
    ModbusRobotFaults,
)
from cellcal.mocks.twins import MODBUS_HOST, RunningTwin, limits_deg

if TYPE_CHECKING:
    from cellcal.drivers.modbus_robot import ModbusRobotOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

__all__ = [
    "ModbusRequest",
    "ModbusRobotFaults",
    "ModbusRobotTwin",
    "floats_to_registers",
    "registers_to_floats",
    "serve",
    "xyzabc",
]

log = logging.getLogger("cellcal.mocks.modbus_robot")


def xyzabc(T_base_flange: np.ndarray) -> np.ndarray:
    """A flange pose (4×4, mm) as the pose registers hold it: [x, y, z] mm and
    [A, B, C] deg, Z-Y-X Euler angles (KUKA's convention)."""
    abc = np.degrees(euler_zyx_from_matrix(T_base_flange[:3, :3]))
    out: np.ndarray = np.concatenate([T_base_flange[:3, 3], abc])
    return out


class _LastRequests(list[ModbusRequest]):
    """The record of requests of a long client, bounded: past ``keep`` (and a quarter
    more, so that trimming is rare) the oldest go."""

    def __init__(self, keep: int) -> None:
        super().__init__()
        self.keep = max(1, keep)

    def append(self, request: ModbusRequest) -> None:
        super().append(request)
        if len(self) > self.keep + self.keep // 4:
            del self[: len(self) - self.keep]


class ModbusRobotTwin(ModbusRobotController):
    """A robot controller behind Modbus TCP; see the module docstring. The constructor,
    inspection and fault injection are the controller's
    (:class:`~cellcal.mocks.modbus.state.ModbusRobotController`); ``requests``
    keeps the last :attr:`REQUEST_LOG` (a twin polled every 2 ms for days would else
    hold every request it ever served)."""

    REQUEST_LOG = 100_000

    _server: TcpLinkServer | None = None
    _address: tuple[str, int] | None = None

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self._requests = _LastRequests(self.REQUEST_LOG)

    @property
    def address(self) -> tuple[str, int]:
        if self._address is None:
            raise RuntimeError("the twin is not running")
        return self._address

    def start(self, host: str = MODBUS_HOST, port: int = 0) -> tuple[str, int]:
        """Serve on ``host:port`` from background threads; returns once listening, with
        the bound address (port 0 picks a free port)."""
        if self._server is not None:
            raise RuntimeError("the twin is already running")
        server = TcpLinkServer(self._serve_link, name=f"modbus-robot-{host}", log=log)
        try:
            self._address = server.start(host, port)
        except OSError as exc:
            server.stop()
            raise RuntimeError(
                f"Modbus robot twin could not listen on {host}:{port}: {exc}"
            ) from exc
        self._server = server
        log.debug("Modbus robot twin listening on %s:%d", *self._address)
        return self._address

    def stop(self) -> None:
        """Stop serving: close the listener and every connection, join the threads;
        idempotent."""
        server, self._server, self._address = self._server, None, None
        if server is not None:
            server.stop()

    def _serve_link(self, link: Link) -> None:
        """One connection: frames in, answers out, until the peer closes, the server
        stops or the framing is lost."""
        pending = b""
        while not link.stop.is_set():
            if not link.wait(POLL_S):
                continue
            data = link.read()
            if data is None:
                return
            split = split_frames(pending + data)
            pending = split.rest
            answers = b"".join(filter(None, map(self._answer, split.frames)))
            if answers:
                link.write(answers)
            if split.error is not None:
                log.warning("Modbus robot twin: %s; closing the connection", split.error)
                return

    def _answer(self, frame: Frame) -> bytes | None:
        """The reply frame to ``frame``; None for a frame of another protocol."""
        if frame.protocol != 0:
            log.info("Modbus robot twin: frame of protocol id %d dropped", frame.protocol)
            return None
        function = frame.pdu[0]
        try:
            if frame.unit != self.device_id:
                raise ModbusError(GATEWAY_TARGET_FAILED, f"unit id {frame.unit}")
            request = decode_request(frame.pdu)
            pdu = reply_pdu(request, self.serve(request))
        except ModbusError as exc:
            log.debug("Modbus robot twin: %s (function %d)", exc, function)
            pdu = exception_pdu(function, exc.code)
        return encode_frame(frame.transaction, frame.unit, pdu)


def serve(options: ModbusRobotOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured Modbus robot: its map, word order and device id, on
    an ephemeral port of a loopback address, following the simulated cell."""
    sim = ModbusRobotTwin(
        q0_deg=list(options.home_deg),
        limits_deg=limits_deg(cell),
        joint_speed_deg_s=math.degrees(cell.joint_speed),
        time_scale=time_scale,
        map=options.map,
        on_move=cell.set_q,
        pose_fn=lambda q: xyzabc(cell.flange_pose(q)),
        faults=ModbusRobotFaults(estop_every=cell.faults.robot_protective_stop_every),
    )
    host, port = sim.start(MODBUS_HOST, 0)
    # On loopback the status can be polled faster than a PLC cycle.
    twin_options = options.model_copy(update={"address": f"{host}:{port}", "poll_s": 0.002})
    return RunningTwin(twin_options, sim)
