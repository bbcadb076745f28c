"""A plain fake KUKA KR C controller behind KUKAVARPROXY, for tests only.

Written from the published KUKAVARPROXY protocol alone (request and reply layouts, the
example read of ``$AXIS_ACT_MEAS``, as docs/robots.md summarises them), never from
cellcal's own KUKA driver or twin: a second, independent server to prove the driver
against.

Wire (big-endian): request ``u16 id, u16 len, u8 fn (0 read, 1 write), u16 n, name
[, u16 m, value]``; reply ``u16 id, u16 len, u8 fn, u16 m, value, u16 0x0001, u8 ok``. A
failed reply has value length 0. Each reply goes out in one ``sendall``. One thread accepts,
one thread serves each connection, one thread runs the cell's KRL loop (``WAIT FOR CC_SEQ <>
CC_ACK``, ``PTP CC_TARGET``, ``CC_ACK = CC_SEQ``). Requests are framed by their length field
whatever the TCP segmentation; a length above 64 KiB (a guard only: a u16 cannot exceed it)
or too short for its own header, or a name/value length that does not fit it, closes that
connection. Names are compared upper-cased; ``requests`` records them as sent. A function
other than 0/1 or an unknown name gets a failed reply.

Choices where the facts leave room (each a little off the simplest form):

- REALs are written ``%.7G``: ``-90`` not ``-90.0``, ``1.5E-05`` for tiny values, ``-0`` never.
- ``$AXIS_ACT_MEAS`` adds fresh uniform noise of at most 0.0004 deg to every read (also while
  moving; fixed seed); its E1..E6 are always present. ``CC_TARGET`` reads back with all twelve axes.
- A ``CC_TARGET`` write must carry A1..A6 (each once); E1..E6 may be absent and then keep
  their previous values, as a KRL aggregate assignment does. Only ``E6AXIS`` or no type name.
- Motion follows a cosine profile (zero speed at both ends); all axes start and stop
  together; duration = largest A-axis travel / (max_speed_deg_s * CC_SPEED/100) * time_scale.
- Leaving #AUT/#EX or switching the drives off mid-move halts the robot where it is; the move
  resumes from there once allowed again (the program sits on the PTP line).
- ``CC_STOP = TRUE`` halts any move, then the loop sets CC_STOP FALSE and CC_ACK = CC_SEQ,
  also when nothing was moving (a pending command is abandoned).
- ``ack_enabled = False``: the loop still executes the move, then hangs on the ``CC_ACK =
  CC_SEQ`` line until it is set True again.
- An out-of-limit target sets ``$STOPMESS`` TRUE and ``$PRO_STATE1`` ``#P_STOP``; nothing
  moves until ``acknowledge_messages()`` (the operator's "acknowledge all") is called.
- System variables (``$...``) are read-only to clients; CC_* variables are writable, CC_ACK
  too. CC_SPEED outside 1..100, INTs outside 32 bits, BOOLs other than TRUE/FALSE fail.
"""

from __future__ import annotations

import contextlib
import math
import random
import re
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence

AXES = ("A1", "A2", "A3", "A4", "A5", "A6", "E1", "E2", "E3", "E4", "E5", "E6")
LIMITS = ((-155, 155), (-180, 65), (-15, 158), (-350, 350), (-130, 130), (-350, 350))
MAX_LEN = 65536
_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_AGG = re.compile(r"\s*\{\s*(?:E6AXIS\s*:)?(.*)\}\s*", re.I | re.S | re.A)
_ITEM = re.compile(rf"\s*([AE][1-6])\s+({_NUM})\s*", re.I | re.A)
_INT = re.compile(r"\s*[+-]?\d+\s*", re.A)


def _real(v: float) -> str:
    return f"{v + 0.0 if v != 0 else 0.0:.7G}"


def _e6axis(vals: list[float]) -> str:
    return "{E6AXIS: " + ", ".join(f"{k} {_real(v)}" for k, v in zip(AXES, vals, strict=True)) + "}"


def _parse_e6axis(text: str, old: list[float]) -> list[float] | None:
    m = _AGG.fullmatch(text)
    if not m:
        return None
    got: dict[str, float] = {}
    for part in m.group(1).split(","):
        im = _ITEM.fullmatch(part)
        if not im or im.group(1).upper() in got or not math.isfinite(float(im.group(2))):
            return None
        got[im.group(1).upper()] = float(im.group(2))
    if any(k not in got for k in AXES[:6]):
        return None
    return [got.get(k, o) for k, o in zip(AXES, old, strict=True)]


def _parse_int(text: str) -> int | None:
    if not _INT.fullmatch(text):
        return None
    v = int(text)
    return v if -(2**31) <= v < 2**31 else None


class KvpFake:
    def __init__(
        self,
        q0_deg: Sequence[float] = (0, -90, 90, 0, 0, 0),
        time_scale: float = 0.0,
        max_speed_deg_s: float = 150.0,
    ) -> None:
        self.time_scale = float(time_scale)
        self.max_speed_deg_s = float(max_speed_deg_s)
        self.mode = "#EX"
        self.drives_on = True
        self.ack_enabled = True
        self.requests: list[tuple[int, str, str | None]] = []
        q = [float(v) for v in q0_deg] + [0.0] * (12 - len(q0_deg))
        self._q = list(q)  # true position when not moving
        self._target = list(q)
        self._seq = self._ack = 0
        self._speed = 10
        self._stop = False
        self._stopmess = False
        self._pro_state = "#P_ACTIVE"
        self._motion: tuple[list[float], list[float], float, float] | None = None
        self._rng = random.Random(7)
        self._cond = threading.Condition()
        self._closing = False
        self._listener: socket.socket | None = None
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []

    # ---- lifecycle -------------------------------------------------------------------
    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((host, port))
        ls.listen(16)
        ls.settimeout(0.05)
        self._listener = ls
        for fn in (self._accept_loop, self._krl_loop):
            t = threading.Thread(target=fn, daemon=True)
            t.start()
            self._threads.append(t)
        bound_host, bound_port = ls.getsockname()[:2]
        return str(bound_host), int(bound_port)

    def stop(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
            conns = list(self._conns)
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
        for t in list(self._threads):
            t.join(5)
        if self._listener is not None:
            self._listener.close()

    def acknowledge_messages(self) -> None:
        with self._cond:
            self._stopmess = False
            self._pro_state = "#P_ACTIVE"
            self._cond.notify_all()

    def q_deg(self) -> list[float]:
        with self._cond:
            return self._q_now()[:6]

    # ---- motion (call with the lock held) --------------------------------------------
    def _q_now(self) -> list[float]:
        if self._motion is None:
            return list(self._q)
        start, goal, t0, dur = self._motion
        u = 1.0 if dur <= 0 else min(1.0, (time.monotonic() - t0) / dur)
        s = (1 - math.cos(math.pi * u)) / 2
        return [a + (b - a) * s for a, b in zip(start, goal, strict=True)]

    def _can_move(self) -> bool:
        return self.mode in ("#AUT", "#EX") and self.drives_on and not self._stopmess

    def _halt(self) -> None:
        self._q = self._q_now()
        self._motion = None

    def _move(self, goal: list[float]) -> None:
        """PTP to goal; returns when there, on CC_STOP, or on close."""
        while True:
            travel = max(abs(b - a) for a, b in zip(self._q[:6], goal[:6], strict=True))
            dur = travel / (self.max_speed_deg_s * self._speed / 100) * self.time_scale
            t0 = time.monotonic()
            self._motion = (list(self._q), list(goal), t0, dur)
            while t0 + dur > time.monotonic():
                if self._closing or self._stop or not self._can_move():
                    break
                self._cond.wait(0.005)
            else:
                self._q, self._motion = list(goal), None
                return
            self._halt()
            while not (self._closing or self._stop or self._can_move()):
                self._cond.wait(0.005)
            if self._closing or self._stop:
                return

    def _krl_loop(self) -> None:
        with self._cond:
            while not self._closing:
                if self._stop:
                    self._halt()
                    self._stop, self._ack = False, self._seq
                elif self._seq != self._ack and self._can_move():
                    goal = list(self._target)
                    if any(not lo <= v <= hi for v, (lo, hi) in zip(goal[:6], LIMITS, strict=True)):
                        self._stopmess, self._pro_state = True, "#P_STOP"
                        continue
                    self._move(goal)
                    while not (self.ack_enabled or self._closing or self._stop):
                        self._cond.wait(0.005)
                    if not (self._closing or self._stop):
                        self._ack = self._seq
                else:
                    self._cond.wait(0.005)

    # ---- variables (call with the lock held) -----------------------------------------
    def _read(self, name: str) -> str | None:
        if name == "$AXIS_ACT_MEAS":
            q = self._q_now()
            return _e6axis([v + self._rng.uniform(-4e-4, 4e-4) for v in q[:6]] + q[6:])
        simple: dict[str, Callable[[], str]] = {
            "CC_TARGET": lambda: _e6axis(self._target),
            "CC_SEQ": lambda: str(self._seq),
            "CC_ACK": lambda: str(self._ack),
            "CC_SPEED": lambda: str(self._speed),
            "CC_STOP": lambda: "TRUE" if self._stop else "FALSE",
            "$MODE_OP": lambda: self.mode,
            "$PERI_RDY": lambda: "TRUE" if self.drives_on else "FALSE",
            "$PRO_STATE1": lambda: self._pro_state,
            "$STOPMESS": lambda: "TRUE" if self._stopmess else "FALSE",
            "$ROB_STOPPED": lambda: "FALSE" if self._motion else "TRUE",
            "$ROBNAME[]": lambda: '"KR5ARC"',
        }
        get = simple.get(name)
        return get() if get else None

    def _write(self, name: str, text: str) -> str | None:
        if name == "CC_TARGET":
            new = _parse_e6axis(text, self._target)
            if new is None:
                return None
            self._target = new
        elif name in ("CC_SEQ", "CC_ACK", "CC_SPEED"):
            v = _parse_int(text)
            if v is None or (name == "CC_SPEED" and not 1 <= v <= 100):
                return None
            setattr(self, {"CC_SEQ": "_seq", "CC_ACK": "_ack", "CC_SPEED": "_speed"}[name], v)
        elif name == "CC_STOP":
            if text.strip().upper() not in ("TRUE", "FALSE"):
                return None
            self._stop = text.strip().upper() == "TRUE"
        else:
            return None
        self._cond.notify_all()
        return self._read(name)

    # ---- network ---------------------------------------------------------------------
    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._closing:
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(None)
            with self._cond:
                if self._closing:
                    conn.close()
                    return
                self._conns.append(conn)
                t = threading.Thread(target=self._serve, args=(conn,), daemon=True)
                self._threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        try:
            while not self._closing:
                while len(buf) >= 4:
                    msg_id, length = struct.unpack_from(">HH", buf)
                    if length > MAX_LEN or length < 3:
                        return
                    if len(buf) < 4 + length:
                        break
                    body, buf = buf[4 : 4 + length], buf[4 + length :]
                    reply = self._handle(msg_id, body)
                    if reply is None:
                        return
                    conn.sendall(reply)
                data = conn.recv(4096)
                if not data:
                    return
                buf += data
        except OSError:
            return
        finally:
            with self._cond:
                if conn in self._conns:
                    self._conns.remove(conn)
            conn.close()

    def _handle(self, msg_id: int, body: bytes) -> bytes | None:
        fn, n = struct.unpack_from(">BH", body)
        if 3 + n > len(body):
            return None
        name = body[3 : 3 + n].decode("latin-1")
        value: str | None = None
        if fn == 1:
            if 5 + n > len(body):
                return None
            (m,) = struct.unpack_from(">H", body, 3 + n)
            if 5 + n + m != len(body):
                return None
            value = body[5 + n : 5 + n + m].decode("latin-1")
        with self._cond:
            self.requests.append((fn, name, value))
            key = name.strip().upper()
            if fn == 0:
                out = self._read(key)
            elif fn == 1 and value is not None:
                out = self._write(key, value)
            else:
                out = None
        raw = out.encode("latin-1") if out is not None else b""
        rest = struct.pack(">BH", fn, len(raw)) + raw + struct.pack(">HB", 1, out is not None)
        return struct.pack(">HH", msg_id, len(rest)) + rest
