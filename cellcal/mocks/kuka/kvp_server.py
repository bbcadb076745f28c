"""The KUKAVARPROXY twin: a KR C4 running cellcal's KRL loop (``mocks/kuka/krc.py``)
behind KUKAVARPROXY's TCP protocol (``drivers/kuka_kvp_wire.py``), on a loopback
address, for the driver, ``cellcal mock kuka-kvp`` and ``cellcal run --mock``.

Like the proxy it serves several clients at once, each connection in a thread of its
own, one request at a time across all of them. Requests are framed by their length
field, whether they arrive split or several in one segment; a reply is written with one
send (a public client, py-openshowvar, reads it with one ``recv``). A request that is not
the protocol (a length beyond 64 KiB or shorter than its own header, a function other
than read and write) closes that connection, as the proxy's socket does. A client that
sends nothing for ``idle_timeout_s`` (60 s) is dropped, as KUKAVARPROXY drops an idle
client (its source, github.com/ImtsSrl/KUKAVARPROXY ``src/frmMain.frm``: the
``tmrHost`` timer and its "IDLE Timeout").
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from cellcal.drivers.kuka_kvp_wire import (
    HEADER,
    READ,
    KvpFrameError,
    decode_request,
    encode_reply,
)
from cellcal.mocks.kuka.krc import KrcController, KrcFaults, krc_for_cell
from cellcal.mocks.link_server import POLL_S, Link, TcpLinkServer
from cellcal.mocks.twins import KUKA_HOST, RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.kuka_kvp import KukaKvpOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.kuka")

MAX_REQUEST = 65536
#: KUKAVARPROXY drops a client idle this long (s)
IDLE_TIMEOUT_S = 60.0


class KvpTwin:
    """KUKAVARPROXY in front of a :class:`KrcController`."""

    def __init__(self, controller: KrcController, idle_timeout_s: float = IDLE_TIMEOUT_S) -> None:
        self.controller = controller
        self.idle_timeout_s = idle_timeout_s
        self.dropped_idle = 0
        self.server = TcpLinkServer(self._handle, name="kuka-kvp-twin", log=log)

    @property
    def faults(self) -> KrcFaults:
        return self.controller.faults

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        return self.server.start(host, port)

    def stop(self) -> None:
        self.server.stop()

    def _handle(self, link: Link) -> None:
        buffer = b""
        heard = time.monotonic()
        while not link.stop.is_set():
            if not link.wait(POLL_S):
                if time.monotonic() - heard > self.idle_timeout_s:
                    log.info("kuka-kvp twin: a client idle for %g s: dropped", self.idle_timeout_s)
                    self.dropped_idle += 1
                    return
                continue
            heard = time.monotonic()
            data = link.read()
            if data is None:
                return
            buffer += data
            while len(buffer) >= HEADER.size:
                msg_id, length = HEADER.unpack_from(buffer)
                if not 3 <= length <= MAX_REQUEST:
                    log.info("kuka-kvp twin: request length %d: closing the connection", length)
                    return
                if len(buffer) < HEADER.size + length:
                    break
                body = buffer[HEADER.size : HEADER.size + length]
                buffer = buffer[HEADER.size + length :]
                try:
                    function, name, value = decode_request(body)
                except KvpFrameError as exc:
                    log.info("kuka-kvp twin: %s: closing the connection", exc)
                    return
                link.write(self._answer(msg_id, function, name, value))

    def _answer(self, msg_id: int, function: int, name: str, value: bytes | None) -> bytes:
        c = self.controller
        with c.lock:
            text = value.decode("ascii", "replace") if value is not None else None
            c.requests.append((function, name, text))
            result = c.read(name) if function == READ else c.write(name, text or "")
        if result is None:
            return encode_reply(msg_id, function, b"", False)
        return encode_reply(msg_id, function, result.encode("ascii"), True)


def serve(options: KukaKvpOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured KUKA robot on an ephemeral port of a loopback address."""
    twin = KvpTwin(krc_for_cell(options.home_deg, cell, time_scale))
    host, port = twin.start(KUKA_HOST, 0)
    twin_options = options.model_copy(update={"address": f"{host}:{port}", "poll_s": 0.005})
    return RunningTwin(twin_options, twin)
