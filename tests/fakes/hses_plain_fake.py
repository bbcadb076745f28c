"""A plain fake Yaskawa controller's High-Speed Ethernet Server (UDP), for tests only.

Written from docs/robots.md ("Yaskawa through the High-Speed Ethernet Server") and the
header and data layouts of the open client hsinkoyu/fs100 (which cites Yaskawa's
manuals), never from cellcal's HSES driver or twin: a second, independent server to prove
the driver against.

A ``socketserver.ThreadingUDPServer``: each datagram is handled on its own thread, the
controller's state under one lock, the motion computed from the clock when asked.

Choices where the description leaves room (each a little off the simplest form):

- Answers carry block number 0x80000000 and the service + 0x80; a refusal is status 0x1F
  with the added status, one word.
- The running bit comes on only ``lag_s`` (30 ms) after a move is accepted, so an early
  status says "not running" while the robot has not left.
- Standing still, the position reads ±1 pulse of jitter (fixed seed).
- ``stale_every``: every N-th answer is preceded by a copy of the previous answer (an old
  request id); ``lose_every``: every N-th request is not answered; ``double_every``: every
  N-th answer is sent twice.
- Motion: linear, 100 deg/s × the speed (0.01 % units) × ``time_scale`` wall seconds per
  second; HOLD freezes it where it is (the move is then abandoned).
- A move whose axis 1 goes beyond ±155° is accepted (status 0), and the robot does not
  leave: alarm 4321 "OVERRUN AXIS S (fake)" until an alarm reset.
- The servo starts off; TEACH and remote-off are switches; with the servo off a move is
  refused (0x2070), in TEACH (0x2080), without remote (0x2100), held (0x2050), with an
  alarm (0x2060).
"""

from __future__ import annotations

import random
import socketserver
import struct
import threading
import time
from typing import Any

HEADER = struct.Struct("<4sHHBBBBI8s")
REQ = struct.Struct("<HHBBH")
ANS = struct.Struct("<BBBBHH")
MOVE = struct.Struct("<22i")


class HsesPlainFake:
    def __init__(
        self, pulses_per_degree: list[float], *, time_scale: float = 0.01, lag_s: float = 0.03
    ) -> None:
        self.ppd = list(pulses_per_degree)
        self.time_scale = time_scale
        self.lag_s = lag_s
        self.teach = False
        self.remote = True
        self.servo = False
        self.hold = False
        self.alarm = 0
        self.lose_every = self.double_every = self.stale_every = 0
        self.deg = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
        self.move: dict[str, Any] | None = None
        self.requests: list[tuple[int, int, int, bytes]] = []  # command, instance, id, data
        self.lost = self.doubled = self.stale = 0
        self.lock = threading.Lock()
        self.rng = random.Random(11)
        self._count = 0
        self._previous = b""
        self._server: socketserver.ThreadingUDPServer | None = None

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        fake = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                data, sock = self.request
                for answer in fake._datagram(data):
                    sock.sendto(answer, self.client_address)

        self._server = socketserver.ThreadingUDPServer((host, port), Handler)
        self._server.daemon_threads = True
        threading.Thread(target=self._server.serve_forever, args=(0.05,), daemon=True).start()
        return host, self._server.server_address[1]

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()

    # ------------------------------------------------------------------ the controller

    def _now(self) -> list[float]:
        """Where the robot is (deg), finishing a move whose time has come."""
        m = self.move
        if m is None:
            return self.deg
        t = (time.monotonic() - m["start"]) / m["seconds"] if m["seconds"] > 0 else 1.0
        if t >= 1.0:
            self.deg, self.move = m["target"], None
            return self.deg
        return [a + (b - a) * t for a, b in zip(m["from"], m["target"], strict=True)]

    def _datagram(self, raw: bytes) -> list[bytes]:
        magic, _, size, _, division, ack, rid, _, _ = HEADER.unpack_from(raw)
        if magic != b"YERC" or ack != 0:
            return []
        command, instance, _, service, _ = REQ.unpack_from(raw, 24)
        data = raw[32 : 32 + size]
        with self.lock:
            self._count += 1
            if self.lose_every and self._count % self.lose_every == 0:
                self.lost += 1
                return []
            self.requests.append((command, instance, rid, data))
            status, added, payload = self._handle(command, instance, data)
            answer = (
                HEADER.pack(b"YERC", 0x20, len(payload), 3, division, 1, rid, 0x80000000,
                            b"99999999")
                + ANS.pack(service + 0x80, status, 1 if added else 0, 0, added, 0)
                + payload
            )  # fmt: skip
            out = [answer]
            if self.double_every and self._count % self.double_every == 0:
                out.append(answer)
                self.doubled += 1
            if self.stale_every and self._previous and self._count % self.stale_every == 0:
                out.insert(0, self._previous)
                self.stale += 1
            self._previous = answer
            return out

    def _handle(self, command: int, instance: int, data: bytes) -> tuple[int, int, bytes]:
        deg = self._now()
        if command == 0x72:
            running = self.move is not None and time.monotonic() - self.move["start"] >= self.lag_s
            d1 = (0x20 if self.teach else 0x40) | (0x80 if self.remote else 0) | (
                0x08 if running else 0)  # fmt: skip
            d2 = (0x08 if self.hold else 0) | (0x10 if self.alarm else 0) | (
                0x40 if self.servo else 0)  # fmt: skip
            return 0, 0, struct.pack("<II", d1, d2)
        if command == 0x75:
            jitter = 0 if self.move is not None else self.rng.choice((-1, 0, 1))
            pulses = [round(d * p) + jitter for d, p in zip(deg, self.ppd, strict=True)]
            return 0, 0, struct.pack("<13i", 0, 0, 0, 0, 0, *pulses, 0, 0)
        if command == 0x8B:
            for refused, added in (
                (self.teach, 0x2080), (not self.remote, 0x2100), (self.alarm != 0, 0x2060),
                (not self.servo, 0x2070), (self.hold, 0x2050),
            ):  # fmt: skip
                if refused:
                    return 0x1F, added, b""
            v = MOVE.unpack(data)
            target = [v[4 + k] / self.ppd[k] for k in range(6)]
            if abs(target[0]) > 155.0:
                self.alarm = 4321
                return 0, 0, b""
            travel = max(abs(a - b) for a, b in zip(target, deg, strict=True))
            speed = 100.0 * v[3] / 10000.0
            seconds = travel / speed * self.time_scale
            self.move = {"from": deg, "target": target, "start": time.monotonic(),
                         "seconds": seconds}  # fmt: skip
            return 0, 0, b""
        if command == 0x83:
            on = struct.unpack("<I", data[:4])[0] == 1
            if instance == 1:
                self.hold = on
                if on and self.move is not None:
                    self.deg, self.move = deg, None
            elif instance == 2:
                self.servo = on
            return 0, 0, b""
        if command == 0x82:
            if instance == 1:
                self.alarm = 0
            return 0, 0, b""
        if command == 0x70:
            text = b"OVERRUN AXIS S (fake)" if self.alarm else b""
            return 0, 0, struct.pack("<III16s32s", self.alarm, 1 if self.alarm else 0,
                                     1 if self.alarm else 0, b"2026/11/28 12:00", text)  # fmt: skip
        return 0x08, 0, b""
