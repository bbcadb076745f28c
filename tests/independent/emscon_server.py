"""A plain Leica emScon TPI server written from the published layout alone (the public
copies of ES_C_API_Def.h, TPI 3.6, as summarised in docs/tracker.md), not from cellcal's
twin or its packet module: every packet is a literal ``struct`` format here, offsets
checked against the header's sizes. It answers what a stationary campaign asks, in its
own way where the protocol leaves room:

* a failing Get* is answered with the short 16-byte basic reply (Leica's own C++
  receiver reads the status before the payload, so a short one is legal; cellcal's twin
  answers full-size);
* results are type 9 in extended statistic mode, type 2 otherwise; the covariance sent
  is a fixed one per target, the meteo a fixed station reading;
* a broken beam is a type 1 error (10009, StartMeasurement) in place of the result, the
  reflector lost until FindReflector or GoBirdBath (no timer);
* lengths in the unit set (metres and millimetres, the two cellcal could meet);
* a second client gets a 10011 error and is closed at once.
"""

from __future__ import annotations

import socket
import struct
import threading

import numpy as np

LE = "<"
HEAD = struct.Struct("<iii")  # size, type, command
BASIC = struct.Struct("<iiii")  # size, type, command, status
#: command id → (parameters' format after the 12-byte head, reply values' format after
#: the 16-byte head), as the header declares them
TABLE = {
    1: ("", "iiiiiiiiii"),  # GetSystemStatus: 56 bytes
    5: ("iiiii", ""),  # SetUnits: 32
    6: ("", "iiiii"),  # GetUnits: 36
    7: ("", ""),  # Initialize
    20: ("ddd", ""),  # SetEnvironmentParams: 36
    24: ("i", ""),  # SetMeasurementMode
    26: ("i", ""),  # SetCoordinateSystemType
    28: ("ii", ""),  # SetStationaryModeParams: 20
    40: ("i", ""),  # SetReflector
    42: ("", "iiid64s"),  # GetReflectors: 100 each
    47: ("iiiiiiiii", ""),  # SetSystemSettings: 48
    48: ("", "iiiiiiiii"),  # GetSystemSettings: 52
    49: ("", ""),  # StartMeasurement
    54: ("", ""),  # GoBirdBath
    63: ("d", ""),  # FindReflector: 20
    80: ("ii", ""),  # SetStatisticMode: 20
    122: ("", "ii"),  # GetMeasurementStatusInfo: 24
    132: ("", "i64siiiiidddiiddiii"),  # GetTrackerInfo: 164
    139: ("", "i64sii"),  # GetMeteoStationInfo: 92
}
RESULT2 = struct.Struct("<iiiii" + "d" * 17)  # type 2: 156 bytes
RESULT9 = struct.Struct("<iiiii" + "d" * 23)  # type 9: 204 bytes


def utf16(name: str) -> bytes:
    return name.encode("utf-16-le").ljust(64, b"\0")


class PlainEmscon:
    """One tracker on ``host``: ``position`` (mm), ``cov`` (mm²); ``break_on`` the
    measurement numbers whose beam breaks; ``cold_for`` the number of GetSystemStatus
    answers that still report the laser heating up (and refuse Initialize)."""

    def __init__(self, host: str, position, cov, *, break_on=(), cold_for: int = 0) -> None:
        self.position = np.asarray(position, dtype=float)
        self.cov = np.asarray(cov, dtype=float)
        self.break_on = set(break_on)
        self.cold_for = cold_for
        self.units = [1, 0, 0, 0, 0]
        self.extended = False
        self.initialized = False
        self.locked = True
        self.count = 0
        self.seen: list[int] = []
        self.busy = threading.Lock()
        self.sock = socket.create_server((host, 0))
        self.address = self.sock.getsockname()
        self._stop = False
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self._stop = True
        self.sock.close()
        self.thread.join(5)

    def _accept(self) -> None:
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            if not self.busy.acquire(blocking=False):
                conn.sendall(BASIC.pack(16, 1, 0, 10011))
                conn.close()
                continue
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            with conn:
                while True:
                    head = self._read(conn, 12)
                    if head is None:
                        return
                    size, _, command = HEAD.unpack(head)
                    body = self._read(conn, size - 12) if size > 12 else b""
                    if body is None:
                        return
                    self.seen.append(command)
                    conn.sendall(self._answer(command, body))
        finally:
            self.busy.release()

    @staticmethod
    def _read(conn: socket.socket, n: int) -> bytes | None:
        data = b""
        while len(data) < n:
            chunk = conn.recv(n - len(data))
            if not chunk:
                return None
            data += chunk
        return data

    def _reply(self, command: int, status: int, *values) -> bytes:
        fmt = TABLE[command][1]
        if status != 0 or not fmt:
            return BASIC.pack(16, 0, command, status)  # short when failing: legal here
        body = struct.pack(LE + fmt, *values)
        return BASIC.pack(16 + len(body), 0, command, 0) + body

    def _answer(self, command: int, body: bytes) -> bytes:
        params = struct.unpack(LE + TABLE[command][0], body) if command in TABLE else ()
        if command == 1:
            laser = 2 if self.cold_for > 0 else 3
            self.cold_for = max(0, self.cold_for - 1)
            proc = 5 if self.initialized else 3
            return self._reply(1, 0, 0, proc, laser, 2, 3, 5, 100, 2, 0, 7001)
        if command == 5:
            self.units = list(params)
            return self._reply(5, 0)
        if command == 6:
            return self._reply(6, 0, *self.units)
        if command == 7:
            if self.cold_for > 0:
                return self._reply(7, 10012)
            self.initialized = True
            return self._reply(7, 0)
        if command == 80:
            self.extended = params[0] == 1
            return self._reply(80, 0)
        if command == 48:
            return self._reply(48, 0, 2, 0, 0, 1, 1, 0, 0, 1, 0)
        if command == 42:
            return b"".join(
                self._reply(42, 0, 2, rid, 5, 0.0, utf16(name))
                for rid, name in ((11, "CCR-1.5in"), (12, "CCR-0.5in"))
            )
        if command == 122:
            flags = 4096 | (65536 if self.initialized else 0) | (2048 if self.locked else 0)
            return self._reply(122, 0, 0, flags)
        if command == 132:
            name = utf16("AT402")
            return self._reply(132, 0, 72, name, 7001, 1, 1, 0, 0, 0.0, 160.0, 0.0, 1000,
                               2, 6.28, 5.0, 1, 2, 1)  # fmt: skip
        if command == 139:
            return self._reply(139, 0, 2, utf16("meteo"), 1, 2)
        if command in (54, 63):
            self.locked = True
            return self._reply(command, 0)
        if command == 49:
            return self._measure()
        return self._reply(command, 0)

    def _measure(self) -> bytes:
        if not self.initialized:
            return self._reply(49, 39)
        if not self.locked:
            return self._reply(49, 10004)
        self.count += 1
        ok = self._reply(49, 0)
        if self.count in self.break_on:
            self.locked = False
            return ok + BASIC.pack(16, 1, 49, 10009)
        k = 0.001 if self.units[0] == 0 else 1.0  # metres or millimetres
        x, y, z = self.position * k
        c = self.cov * k * k
        s1, s2, s3 = np.sqrt(np.diag(c))
        air = (21.25, 1008.5, 37.0)
        if self.extended:
            values = [x, y, z, s1, s2, s3, 0.0, c[0, 1], c[0, 2], c[1, 2], 0.0, 0.0, 0.0,
                      s1, s2, s3, 0.0, c[0, 1], c[0, 2], c[1, 2], *air]  # fmt: skip
            return ok + RESULT9.pack(204, 9, 0, 0, 0, *values)
        values = [x, y, z, s1, s2, s3, 0.0, 0.0, 0.0, 0.0, s1, s2, s3, 0.0, *air]
        return ok + RESULT2.pack(156, 2, 0, 0, 0, *values)
