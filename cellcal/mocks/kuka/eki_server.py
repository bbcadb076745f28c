"""The EthernetKRL twin: a KR C4 running ``CellCalEki.src`` (the controller of
``mocks/kuka/krc.py``, the same loop as behind KUKAVARPROXY) as the TCP server of its
EthernetKRL channel, for the ``kuka-eki`` driver, ``cellcal mock kuka-eki`` and
``cellcal run --mock``.

As the channel the shipped XML configuration declares: one client at a time (a second
connection is accepted and closed at once, as EthernetKRL's server does while its one
connection is up); a state telegram every ``cycle_s`` (50 ms, the KRL timer interrupt's
period; in mock mode scaled like the motion, 2 ms at the least) from the connection on;
a ``<Cmd>`` writes the target, the speed and the sequence number the loop answers; a
``<Stop>`` brakes the running move. A telegram that is not one of cellcal's is logged
and dropped (EthernetKRL reports an XML error on the pendant and keeps the connection).
In T1/T2 a command is ignored (the loop's variables are not written from outside in the
manual modes).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from cellcal.drivers.kuka_eki_wire import (
    EkiState,
    EkiTelegramError,
    format_state,
    parse_command,
    split_telegrams,
)
from cellcal.drivers.kuka_kvp_wire import format_axes
from cellcal.mocks.kuka.krc import KrcController, krc_for_cell
from cellcal.mocks.link_server import Link, TcpLinkServer
from cellcal.mocks.twins import KUKA_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.kuka_eki import KukaEkiOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.kuka")

CYCLE_S = 0.05


class EkiTwin:
    """The EthernetKRL channel of a :class:`KrcController`."""

    def __init__(self, controller: KrcController, cycle_s: float = CYCLE_S) -> None:
        self.controller = controller
        self.cycle_s = cycle_s
        self.server = TcpLinkServer(self._handle, name="kuka-eki-twin", log=log)
        self._busy = threading.Lock()
        self.refused = 0  # connections closed because another one held the channel

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        return self.server.start(host, port)

    def stop(self) -> None:
        self.server.stop()

    def state(self) -> EkiState:
        c = self.controller
        with c.lock:
            c.step()
            q = c.q_now()
            f = c.faults
            return EkiState(
                seq=c.seq,
                ack=c.ack,
                mode=f.mode,
                drives=f.drives_on,
                estop=False,
                guard_stop=False,
                in_motion=c.move is not None,
                rob_stopped=c.move is None,
                program="#P_STOP" if c.stop_message else "#P_ACTIVE",
                stop_message=c.stop_message,
                axes_deg=tuple(float(v) for v in q),
            )

    def _handle(self, link: Link) -> None:
        # a client that has just closed its link may still hold the channel for the
        # instant its session takes to read the end: a new one waits that long
        if not self._busy.acquire(timeout=2 * self.cycle_s):
            self.refused += 1
            log.info("kuka-eki twin: a second client while the channel is up: closed")
            return
        try:
            self._serve(link)
        finally:
            self._busy.release()

    def _serve(self, link: Link) -> None:
        buffer = b""
        next_send = time.monotonic()
        while not link.stop.is_set():
            now = time.monotonic()
            if now >= next_send:
                link.write(format_state(self.state()))
                next_send = now + self.cycle_s
            if not link.wait(max(0.0, next_send - time.monotonic())):
                continue
            data = link.read()
            if data is None:
                return
            try:
                telegrams, buffer = split_telegrams(buffer + data)
            except EkiTelegramError as exc:
                log.info("kuka-eki twin: %s: buffer dropped", exc)
                telegrams, buffer = [], b""
            for raw in telegrams:
                self._command(raw)

    def _command(self, raw: bytes) -> None:
        try:
            cmd = parse_command(raw)
        except EkiTelegramError as exc:
            log.info("kuka-eki twin: XML error, telegram dropped: %s", exc)
            return
        c = self.controller
        with c.lock:
            if cmd.target_deg is None:
                c.write("CC_STOP", "TRUE")
                return
            c.write("CC_TARGET", format_axes(list(cmd.target_deg)))
            c.write("CC_SPEED", str(cmd.speed))
            c.write("CC_SEQ", str(cmd.seq))


def serve(options: KukaEkiOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured KUKA robot on an ephemeral port of a loopback address."""
    # the 50 ms period runs on the simulated clock, as the motion does (2 ms at the least)
    cycle_s = max(0.002, CYCLE_S * time_scale)
    twin = EkiTwin(krc_for_cell(options.home_deg, cell, time_scale), cycle_s=cycle_s)
    host, port = twin.start(KUKA_HOST, 0)
    twin_options = options.model_copy(update={"address": f"{host}:{port}", "poll_s": 0.005})
    return RunningTwin(twin_options, twin)
