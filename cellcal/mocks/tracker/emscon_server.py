"""The emScon twin (``cellcal mock tracker --dialect emscon``): the simulated cell's
tracker served as a Leica emScon TPI server over TCP — the tracker's answers are
``emscon_state.py``'s, this module moves the bytes.

One client at a time, as a real tracker: a second connection is sent the error packet
"multi connections not allowed" (10011) and closed (after a second's grace, in case
the first has just closed), the first one goes on. A packet
whose announced size no packet of the protocol has ends the connection (a client out of
step cannot be trusted to be in step again); a command of the wrong size or an unknown
one is answered with an error packet ("wrong parameter") and the connection goes on.
When the client goes, what it left pending (a result, an initialisation's end) is
dropped; the tracker (initialised, its settings) stays as it was.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers import emscon_packets as p
from cellcal.mocks.link_server import JOIN_S, POLL_S, Link, TcpLinkServer
from cellcal.mocks.tracker.emscon_state import EmsconFaults, EmsconState
from cellcal.mocks.twins import TRACKER_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.emscon import EmsconOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.tracker.emscon")

#: How long a new connection waits for the client before it to be gone (s).
HANDOVER_S = 1.0


class EmsconTwin:
    """A tracker (:class:`EmsconState`) behind a TCP port. ``commands`` keeps the last
    :attr:`LOG` command ids received, for tests."""

    LOG = 10000

    def __init__(self, state: EmsconState) -> None:
        self.state = state
        self._lock = threading.Lock()
        self._client: Link | None = None
        self._stop = threading.Event()
        self._commands: deque[int] = deque(maxlen=self.LOG)
        self.refused = 0
        #: where it listens, once started
        self.address: tuple[str, int] | None = None
        self._tcp = TcpLinkServer(self._serve, name="emscon-twin", stop=self._stop, log=log)

    @property
    def commands(self) -> list[int]:
        with self._lock:
            return list(self._commands)

    @property
    def connections(self) -> int:
        return self._tcp.connections

    def start_tcp(self, host: str = TRACKER_HOST, port: int = 0) -> tuple[str, int]:
        """Listen on (host, port) (0: any free port); the bound address once listening."""
        self.address = self._tcp.start(host, port)
        return self.address

    def stop(self) -> None:
        self._stop.set()
        self._tcp.stop(JOIN_S)

    def __enter__(self) -> EmsconTwin:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- one connection

    def _serve(self, link: Link) -> None:
        # a client that has just closed may not be seen gone yet: a moment's grace
        deadline = time.monotonic() + HANDOVER_S
        while True:
            with self._lock:
                if self._client is None:
                    self._client = link
                    break
            if time.monotonic() >= deadline:
                with self._lock:
                    self.refused += 1
                link.write(p.encode_error(0, p.MULTI_CONNECTIONS_NOT_ALLOWED))
                return
            time.sleep(POLL_S / 5)
        try:
            self._session(link)
        finally:
            with self._lock:
                self._client = None
                self.state.pending.clear()
                self.state.busy_until = None

    def _session(self, link: Link) -> None:
        buf = b""
        while not link.stop.is_set():
            now = time.monotonic()
            with self._lock:
                out = self.state.due(now)
                due = self.state.next_due()
            for data in out:
                link.write(data)
            wait = POLL_S if due is None else min(POLL_S, max(0.0, due - now))
            if not link.wait(wait):
                continue
            chunk = link.read()
            if chunk is None:
                return  # the client closed
            buf += chunk
            while len(buf) >= p.HEADER.size:
                size, _ = p.HEADER.unpack_from(buf)
                if size < p.COMMAND_HEAD.size or size > p.MAX_PACKET:
                    log.warning("emscon twin: a packet announces %d bytes; closing", size)
                    return
                if len(buf) < size:
                    break
                packet, buf = buf[:size], buf[size:]
                for data in self._answer(packet):
                    link.write(data)

    def _answer(self, packet: bytes) -> list[bytes]:
        command = p.COMMAND_HEAD.unpack_from(packet)[2]
        try:
            decoded = p.decode_command(packet)
        except p.PacketError as exc:
            log.info("emscon twin: %s", exc)
            return [p.encode_error(command, p.WRONG_PARAMETER)]
        with self._lock:
            self._commands.append(decoded.command)
            return self.state.handle(decoded, time.monotonic())


def noise_covariance(cell: SimulatedCell, sensor: str) -> Array:
    """The covariance (mm²) of the simulated cell's tracker noise where the target is now:
    σ_radial along the beam, σ_transverse × range across it (``SimulatedCell.sample``)."""
    s = cell.sensors[sensor]
    position = cell.true_position(sensor)
    r = float(np.linalg.norm(position))
    u = position / r
    st = s.sigma_transverse_per_mm * r
    out: Array = s.sigma_radial**2 * np.outer(u, u) + st**2 * (np.eye(3) - np.outer(u, u))
    return out


def emscon_twin(cell: SimulatedCell, sensor: str, time_scale: float) -> EmsconTwin:
    """The simulated cell's tracker ``sensor`` as an emScon twin (not yet listening), its
    faults from ``[simulation.faults]``; its warm-up starts now."""
    f = cell.faults
    faults = EmsconFaults(
        warmup_s=f.tracker_warmup_s,
        beam_break_every=f.tracker_beam_break_every,
        beam_restore_s=f.tracker_beam_restore_s,
    )
    state = EmsconState(
        sample=lambda: cell.sample(sensor, 1)[0],
        covariance=lambda: noise_covariance(cell, sensor),
        started=time.monotonic(),
        faults=faults,
        time_scale=time_scale,
    )
    return EmsconTwin(state)


def serve(options: EmsconOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of a configured emScon tracker: the simulated cell's target of this
    sensor, served on a loopback address; its faults from ``[simulation.faults]``."""
    server = emscon_twin(cell, options.name, time_scale)
    host, port = server.start_tcp(TRACKER_HOST, 0)
    return RunningTwin(options.model_copy(update={"address": f"{host}:{port}"}), server)
