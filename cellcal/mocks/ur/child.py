"""The UR twin's child process: one selector loop that serves RTDE (30004), the
dashboard (29999) and the script port (30003) on one host address, runs the controller
cycle every 2 ms, and talks to the parent over stdin/stdout in JSON lines.

Why a child process: pybind11 holds the GIL in ur_rtde's constructors
(``RTDEReceiveInterface(host)``, ``RTDEControlInterface(host)``), which block until the
controller has answered (first data package, script running). A server made of Python
threads in the same interpreter as the client cannot answer then, and the constructor
never returns. So the wire protocols and the controller state run here, and the
kinematics and the ``on_move`` hook stay in the parent (:mod:`cellcal.mocks.ur.server`).

The cycle: every 2 ms of wall time the controller steps once (:meth:`Controller.step`),
then each started RTDE connection gets the data packages its recipes' frequencies pick
for that cycle, and each script-port connection the real-time packet. A loop that falls
behind runs the missed cycles back to back (each with its own timestamp), up to 50 ms;
beyond that the backlog is dropped, as a controller short of time skips packages. So
``timestamp`` is always a whole number of 2 ms cycles, and consecutive packages of a
recipe at f Hz are 500/f cycles apart.

Output that a client does not read is dropped rather than queued without bound: an RTDE
connection whose unsent data passes 256 KiB gets no data packages until it drains, and
a script-port connection gets a real-time packet only when the previous one has gone.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import selectors
import signal
import socket
import sys
import time
from typing import Any

from cellcal.mocks.ur import rtde_codec as rtde
from cellcal.mocks.ur.controller import Controller
from cellcal.mocks.ur.dashboard import DASHBOARD_PORT, WELCOME, Dashboard
from cellcal.mocks.ur.rtde_session import RtdeSession
from cellcal.mocks.ur.script_port import SCRIPT_PORT, ScriptReader, realtime_packet

log = logging.getLogger("cellcal.mocks.ur")
#: Replies waiting for a client that reads none of them: past this (bytes) the client is
#: closed (a client that asks and never reads would grow them without bound).
MAX_UNREAD = 1 << 20

RTDE_BACKLOG = 262144  # bytes of unsent RTDE data past which packages are dropped
MAX_CATCH_UP = 25  # cycles run back to back when the loop is late (50 ms)


class _Conn:
    def __init__(self, kind: str, sock: socket.socket, cid: int) -> None:
        self.kind = kind
        self.sock = sock
        self.cid = cid
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.closed = False
        self.rtde: RtdeSession | None = None
        self.script: ScriptReader | None = None


class ChildLoop:
    """Sockets, the parent pipe and the 2 ms cycle around one :class:`Controller`."""

    def __init__(self, cfg: dict[str, Any], out_fd: int) -> None:
        self.host: str = cfg["host"]
        self.ctl = Controller(cfg, self.to_parent)
        self.dashboard = Dashboard(self.ctl)
        self.input_owners: dict[str, int] = {}
        self.running = True
        self.sel = selectors.DefaultSelector()
        self.conns: dict[int, _Conn] = {}
        self.next_cid = 1
        self.out_fd = out_fd
        self.parent_out = bytearray()
        self.parent_in = bytearray()
        self.parent_writing = False

    # -- parent link --------------------------------------------------------------------

    def to_parent(self, msg: dict[str, Any]) -> None:
        self.parent_out += (json.dumps(msg) + "\n").encode()
        self._flush_parent()

    def _flush_parent(self) -> None:
        while self.parent_out:
            try:
                n = os.write(self.out_fd, self.parent_out)
            except BlockingIOError:
                break
            except OSError:
                self.running = False
                self.parent_out.clear()
                return
            del self.parent_out[:n]
        want = bool(self.parent_out)
        if want != self.parent_writing:
            self.parent_writing = want
            if want:
                self.sel.register(self.out_fd, selectors.EVENT_WRITE, ("parent_out", None))
            else:
                self.sel.unregister(self.out_fd)

    def _read_parent(self) -> None:
        try:
            data = os.read(0, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self.running = False
            return
        self.parent_in += data
        while b"\n" in self.parent_in:
            line, _, rest = self.parent_in.partition(b"\n")
            self.parent_in = bytearray(rest)
            if line.strip() and not self.ctl.on_parent(json.loads(line)):
                self.running = False

    # -- the loop -----------------------------------------------------------------------

    def listen(self) -> None:
        ports = (("rtde", rtde.RTDE_PORT), ("dash", DASHBOARD_PORT), ("script", SCRIPT_PORT))
        for kind, port in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, port))
            except OSError as e:
                s.close()
                raise OSError(f"cannot bind {self.host}:{port}: {e.strerror or e}") from e
            s.listen(16)
            s.setblocking(False)
            self.sel.register(s, selectors.EVENT_READ, ("listen", kind))

    def run(self) -> None:
        os.set_blocking(0, False)
        os.set_blocking(self.out_fd, False)
        self.sel.register(0, selectors.EVENT_READ, ("parent_in", None))
        next_tick = time.monotonic() + rtde.CYCLE_S
        while self.running:
            timeout = max(0.0, next_tick - time.monotonic())
            for key, mask in self.sel.select(timeout):
                what, data = key.data
                if what == "listen":
                    self._accept(key.fileobj, data)  # type: ignore[arg-type]
                elif what == "parent_in":
                    self._read_parent()
                elif what == "parent_out":
                    self._flush_parent()
                else:
                    conn: _Conn = data
                    if mask & selectors.EVENT_READ:
                        self._on_readable(conn)
                    if mask & selectors.EVENT_WRITE and not conn.closed:
                        self._flush(conn)
                if not self.running:
                    break
            late = 0
            while self.running and time.monotonic() >= next_tick:
                self.cycle()
                next_tick += rtde.CYCLE_S
                late += 1
                if late >= MAX_CATCH_UP:
                    next_tick = max(next_tick, time.monotonic() + rtde.CYCLE_S)
        for conn in list(self.conns.values()):
            self._close(conn)
        for key in list(self.sel.get_map().values()):
            if key.data[0] == "listen":
                self.sel.unregister(key.fileobj)
                key.fileobj.close()  # type: ignore[union-attr]

    def cycle(self) -> None:
        """One controller cycle: step, then every connection's outputs."""
        self.ctl.step()
        packet: bytes | None = None
        for conn in list(self.conns.values()):
            if conn.closed:
                continue
            if conn.rtde is not None and conn.rtde.started:
                frames = conn.rtde.cycle()
                if frames and len(conn.outbuf) <= RTDE_BACKLOG:
                    self._queue(conn, b"".join(frames))
            elif conn.kind == "script" and not conn.outbuf:
                packet = packet or realtime_packet(self.ctl)
                self._queue(conn, packet)
        self.ctl.after_outputs()

    # -- connections --------------------------------------------------------------------

    def _accept(self, lsock: socket.socket, kind: str) -> None:
        try:
            sock, _addr = lsock.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        if kind != "dash":
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Conn(kind, sock, self.next_cid)
        self.next_cid += 1
        if kind == "rtde":
            conn.rtde = RtdeSession(conn.cid, self.ctl.fields, self.input_owners, self.host)
        elif kind == "script":
            conn.script = ScriptReader(self.ctl)
        self.conns[conn.cid] = conn
        self.sel.register(sock, selectors.EVENT_READ, ("conn", conn))
        log.debug("UR twin %s: %s connection %d", self.host, kind, conn.cid)
        if kind == "dash":
            self._queue(conn, (WELCOME + "\n").encode())

    def _close(self, conn: _Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        with contextlib.suppress(KeyError, ValueError):
            self.sel.unregister(conn.sock)
        conn.sock.close()
        self.conns.pop(conn.cid, None)
        if conn.rtde is not None:
            conn.rtde.close()

    def _queue(self, conn: _Conn, data: bytes) -> None:
        if conn.closed:
            return
        if len(conn.outbuf) + len(data) > MAX_UNREAD:
            log.warning(
                "UR twin %s: %s connection %d does not read its replies; closing",
                self.host, conn.kind, conn.cid,
            )  # fmt: skip
            self._close(conn)
            return
        conn.outbuf += data
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        try:
            while conn.outbuf:
                n = conn.sock.send(conn.outbuf)
                del conn.outbuf[:n]
        except BlockingIOError:
            return  # the socket is full: the rest goes when the selector says writable
        except OSError:
            self._close(conn)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.outbuf else 0)
        with contextlib.suppress(KeyError, ValueError):
            self.sel.modify(conn.sock, events, ("conn", conn))

    def _on_readable(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            log.debug("UR twin %s: %s connection %d closed", self.host, conn.kind, conn.cid)
            self._close(conn)
            return
        if conn.rtde is not None:
            conn.inbuf += data
            try:
                for mtype, payload in rtde.split_frames(conn.inbuf):
                    replies = conn.rtde.handle(mtype, payload)
                    if replies:
                        self._queue(conn, b"".join(replies))
            except ValueError as e:
                log.warning("UR twin %s: %s; closing", self.host, e)
                self._close(conn)
        elif conn.script is not None:
            conn.script.feed(data)
        else:
            conn.inbuf += data
            self._dashboard_input(conn)

    def _dashboard_input(self, conn: _Conn) -> None:
        while b"\n" in conn.inbuf and not conn.closed:
            raw, _, rest = conn.inbuf.partition(b"\n")
            conn.inbuf = bytearray(rest)
            line = raw.decode("utf-8", "replace").strip()
            reply, close = self.dashboard.answer(line)
            self._queue(conn, (reply + "\n").encode())
            if close:
                self._flush(conn)
                self._close(conn)
        if len(conn.inbuf) > 4096:
            log.warning(
                "UR twin %s: dashboard connection %d sent a line over 4096 bytes; closing",
                self.host, conn.cid,
            )  # fmt: skip
            self._close(conn)


def child_main(cfg_json: str) -> int:
    """Entry point of the child process (see the module docstring)."""
    cfg = json.loads(cfg_json)
    # Keep the protocol pipe private: stray prints go to stderr.
    out_fd = os.dup(1)
    os.dup2(2, 1)
    logging.basicConfig(
        level=int(cfg.get("log_level", logging.WARNING)),
        format="%(asctime)s %(levelname)s [ur-sim %(process)d] %(message)s",
        stream=sys.stderr,
    )
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    loop = ChildLoop(cfg, out_fd)
    try:
        loop.listen()
    except OSError as e:
        os.write(out_fd, (json.dumps({"t": "error", "msg": str(e)}) + "\n").encode())
        return 1
    os.write(out_fd, b'{"t": "listening"}\n')
    loop.run()
    return 0
