"""A TCP proxy on a loopback address of the fleet tests' own, between a cell and its
PostgreSQL server, that can cut the network: after so many bytes from the cell (in the
middle of a COPY), or at once; while cut, new connections are refused (its listening
socket closed), as a pulled cable or a down link would have them."""

from __future__ import annotations

import contextlib
import socket
import threading


class CuttingProxy:
    def __init__(self, host: str, target: tuple[str, int]) -> None:
        self.host = host
        self.target = target
        self.port = 0
        self.cut_after: int | None = None  # bytes from the cell, then the link is cut
        self._sent = 0
        self._lock = threading.Lock()
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._server: socket.socket | None = None
        self._acceptor = threading.current_thread()
        self.listen()

    def listen(self) -> None:
        """Accept again (on the same port once it had one)."""
        self.cut()
        server = socket.create_server((self.host, self.port), reuse_port=False)
        server.settimeout(0.2)
        self.port = server.getsockname()[1]
        self._server = server
        self._sent = 0
        self._acceptor = threading.Thread(target=self._accept, args=(server,), daemon=True)
        self._acceptor.start()

    def cut(self) -> None:
        """Every connection dropped, none accepted until :meth:`listen`."""
        with self._lock:
            server, self._server = self._server, None
            pairs, self._pairs = self._pairs, []
        if server is not None:
            with contextlib.suppress(OSError):
                server.shutdown(socket.SHUT_RDWR)  # wakes the accepting thread
            server.close()
            # the kernel keeps the port listening until that thread has let go of it
            if self._acceptor is not threading.current_thread():
                self._acceptor.join(5)
        for a, b in pairs:
            for s in (a, b):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()

    def _accept(self, server: socket.socket) -> None:
        while self._server is server:
            try:
                client, _ = server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                upstream = socket.create_connection(self.target, timeout=10)
            except OSError:  # the server is down: so is this connection
                client.close()
                continue
            with self._lock:
                self._pairs.append((client, upstream))
            threading.Thread(target=self._pipe, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pipe, args=(upstream, client, False), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, from_cell: bool) -> None:
        try:
            with contextlib.suppress(OSError):  # a cut link ends this direction
                while data := src.recv(65536):
                    if from_cell and self.cut_after is not None:
                        with self._lock:
                            self._sent += len(data)
                            over = self._sent > self.cut_after
                        if over:
                            self.cut()
                            return
                    dst.sendall(data)
        finally:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        self.cut()
