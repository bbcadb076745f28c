"""A plain fake KUKA KR C controller running ``CellCalEki`` over EthernetKRL, for tests only.

Written from ``docs/robots.md`` ("KUKA through EthernetKRL") and the exported program
(``CellCalEki.xml``, ``CellCalEki.src``) alone, never from cellcal's own EthernetKRL driver or
twin: a second, independent server to prove the driver against.

The controller is the TCP server and takes one client at a time; a second connection while
one is up is accepted and closed at once (counted in ``refused``). From the moment a client
connects it gets a state telegram every ``cycle_s`` (the first one at once), each followed by
``\\r\\n``. One thread accepts, one serves the connection (sends and reads), one runs the KRL
loop of ``CellCalEki.src`` (take a ``<Cmd>``, ``CC_EKI_SEQ = Seq``, ``PTP``, ``CC_EKI_ACK =
Seq``). Client telegrams are framed by ``</CellCal>`` whatever the TCP segmentation; more
than 4096 bytes (the channel's BUFFSIZE) without one closes the connection.

Choices where the published description leaves room (each a little off the simplest form):

- Flags are written ``TRUE``/``FALSE``; REALs ``%.9g`` (``-90``, ``12.0003417``).
- ``$AXIS_ACT_MEAS`` adds fresh uniform noise of at most 0.00035 deg (fixed seed) to every
  telegram, so the %.9g rounding cannot take it over 0.0004 deg. ``q_deg()`` is noise-free.
- Every telegram ending in ``</CellCal>`` is recorded in ``commands`` (stripped), even the
  ones then dropped. A telegram is dropped unless it parses as XML with a ``CellCal`` root
  holding exactly one ``Cmd`` or ``Stop`` with the declared attributes (INTs ``[+-]digits``,
  finite REALs); undeclared attributes are ignored, as EthernetKRL ignores undeclared
  elements; ``<!`` (DOCTYPE, entity) anywhere drops it too.
- Commands queue in arrival order (the channel buffers them); the loop takes one at a time.
  ``Speed`` outside 1..100 becomes 10, as the program does.
- The loop sets ``Seq`` when it takes a command, then checks the limits: a target outside
  them sets ``StopMess`` TRUE and ``Program`` ``#P_STOP``; it is never executed nor
  acknowledged. ``acknowledge_messages()`` clears the message and sets ``#P_ACTIVE`` again.
- Motion follows a smoothstep profile; all axes start and stop together. The program moves
  only while the mode is ``#AUT``/``#EX``, the drives are on, no e-stop, no guard stop and
  no stop message: otherwise a taken command waits on its PTP line, and a running move
  pauses where it is and resumes once allowed again (its clock stops meanwhile).
- ``<Stop>`` brakes (at once) the move the loop has taken, also one waiting at its PTP
  line, and the loop acknowledges it (``Ack`` = the ``Cmd``'s Seq; the Stop's own Seq is
  not used). With no move taken it changes nothing; queued commands stay queued.
- ``hang = True``: moves still run, but the loop waits on the ``CC_EKI_ACK = seq`` line
  until ``hang`` is False again.
- The program's state (position, Seq, Ack, queue) survives a client disconnecting.
"""

from __future__ import annotations

import contextlib
import math
import random
import re
import select
import socket
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence

AXES = ("A1", "A2", "A3", "A4", "A5", "A6")
LIMITS = ((-170, 170), (-190, 45), (-120, 156), (-185, 185), (-120, 120), (-350, 350))
MAX_AXIS_SPEED = 150.0  # deg/s at Speed=100
NOISE = 0.00035
BUFFSIZE = 4096
_END = b"</CellCal>"
_INT = re.compile(r"[+-]?\d+", re.A)
_REAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.A)


def _flag(b: bool) -> str:
    return "TRUE" if b else "FALSE"


def _parse(text: str) -> tuple[str, int, int, list[float]] | None:
    """``("Cmd", seq, speed, target)`` or ``("Stop", seq, 0, [])``; None if not a command."""
    if "<!" in text:
        return None
    try:
        root = ET.fromstring(text)
    except ET.ParseError:
        return None
    if root.tag != "CellCal" or len(root) != 1 or (root.text or "").strip():
        return None
    el = root[0]
    if len(el) or (el.text or "").strip() or (el.tail or "").strip():
        return None
    if el.tag == "Stop" and _INT.fullmatch(el.get("Seq", "")):
        return ("Stop", int(el.get("Seq", "")), 0, [])
    if el.tag != "Cmd":
        return None
    if not all(_INT.fullmatch(el.get(k, "")) for k in ("Seq", "Speed")):
        return None
    if not all(_REAL.fullmatch(el.get(k, "")) for k in AXES):
        return None
    target = [float(el.get(k, "")) for k in AXES]
    if not all(math.isfinite(v) for v in target):
        return None
    return ("Cmd", int(el.get("Seq", "")), int(el.get("Speed", "")), target)


class EkiFake:
    def __init__(
        self,
        q0_deg: Sequence[float] = (0, -90, 90, 0, 0, 0),
        time_scale: float = 0.0,
        cycle_s: float = 0.05,
    ) -> None:
        self.mode = "#AUT"
        self.drives = True
        self.estop = False
        self.guard_stop = False
        self.hang = False
        self.commands: list[str] = []
        self.refused = 0
        self._time_scale = float(time_scale)
        self._cycle = float(cycle_s)
        self._q = [float(v) for v in q0_deg]
        self._seq = 0
        self._ack = 0
        self._stopmess = False
        self._program = "#P_ACTIVE"
        self._moving = False
        self._taken = False  # the loop holds a command (inside CC_EKI_MOVE)
        self._brake = False
        self._queue: list[tuple[int, int, list[float]]] = []
        self._rng = random.Random(1955)
        self._lock = threading.Condition()
        self._halt = threading.Event()
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._threads: list[threading.Thread] = []

    # -- public ----------------------------------------------------------------------------

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(4)
        sock.settimeout(0.1)
        self._listener = sock
        for target in (self._accept_loop, self._krl_loop):
            t = threading.Thread(target=target, daemon=True, name=f"eki-fake-{target.__name__}")
            t.start()
            self._threads.append(t)
        addr = sock.getsockname()
        return addr[0], addr[1]

    def stop(self) -> None:
        self._halt.set()
        with self._lock:
            self._lock.notify_all()
            client = self._client
        if client is not None:
            with contextlib.suppress(OSError):
                client.shutdown(socket.SHUT_RDWR)
        for t in self._threads:
            t.join(timeout=2.0)
        if self._listener is not None:
            self._listener.close()

    def acknowledge_messages(self) -> None:
        with self._lock:
            self._stopmess = False
            self._program = "#P_ACTIVE"
            self._lock.notify_all()

    @property
    def busy(self) -> bool:
        """Whether a client holds the channel (it takes one at a time)."""
        with self._lock:
            return self._client is not None

    def q_deg(self) -> list[float]:
        with self._lock:
            return list(self._q)

    # -- the KRL program -------------------------------------------------------------------

    def _can_move(self) -> bool:
        return (
            self.mode in ("#AUT", "#EX")
            and self.drives
            and not self.estop
            and not self.guard_stop
            and not self._stopmess
        )

    def _krl_loop(self) -> None:
        while not self._halt.is_set():
            with self._lock:
                if not self._queue:
                    self._lock.wait(0.05)
                    continue
                seq, speed, target = self._queue.pop(0)
                self._seq = seq
                if any(not lo <= v <= hi for v, (lo, hi) in zip(target, LIMITS, strict=True)):
                    self._stopmess = True
                    self._program = "#P_STOP"
                    continue
                self._taken, self._brake = True, False
            self._move(target, speed if 1 <= speed <= 100 else 10)
            while self.hang and not self._halt.is_set():
                time.sleep(0.005)
            with self._lock:
                self._ack = seq

    def _move(self, target: list[float], speed: int) -> None:
        with self._lock:
            start = list(self._q)
        travel = max(abs(b - a) for a, b in zip(start, target, strict=True))
        duration = travel / (MAX_AXIS_SPEED * speed / 100.0) * self._time_scale
        elapsed, last = 0.0, time.monotonic()
        while True:
            with self._lock:
                now = time.monotonic()
                if self._halt.is_set() or self._brake:
                    self._taken = self._moving = self._brake = False
                    return
                if self._can_move():
                    elapsed += now - last
                    s = 1.0 if elapsed >= duration else elapsed / duration
                    s = s * s * (3.0 - 2.0 * s)
                    self._q = [a + (b - a) * s for a, b in zip(start, target, strict=True)]
                    self._moving = s < 1.0
                    if not self._moving:
                        self._q = list(target)
                        self._taken = False
                        return
                else:
                    self._moving = False
                last = now
            time.sleep(0.002)

    # -- the channel -----------------------------------------------------------------------

    def _telegram(self) -> bytes:
        with self._lock:
            q = [v + self._rng.uniform(-NOISE, NOISE) for v in self._q]
            moving = self._moving
            head = (
                f'Seq="{self._seq}" Ack="{self._ack}" Mode="{self.mode}" '
                f'Drives="{_flag(self.drives)}" EStop="{_flag(self.estop)}" '
                f'GuardStop="{_flag(self.guard_stop)}" InMotion="{_flag(moving)}" '
                f'RobStopped="{_flag(not moving)}" Program="{self._program}" '
                f'StopMess="{_flag(self._stopmess)}"'
            )
        axis = " ".join(f'{k}="{v:.9g}"' for k, v in zip(AXES, q, strict=True))
        return f"<CellCal><State {head}/><Axis {axis}/></CellCal>\r\n".encode("ascii")

    def _handle(self, raw: bytes) -> None:
        text = raw.decode("utf-8", "replace").strip()
        parsed = _parse(text)
        with self._lock:
            self.commands.append(text)
            if parsed is None:
                return
            kind, seq, speed, target = parsed
            if kind == "Stop":
                if self._taken:
                    self._brake = True
            else:
                self._queue.append((seq, speed, target))
            self._lock.notify_all()

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._halt.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                busy = self._client is not None
                if not busy:
                    self._client = conn
            if busy:  # counted before the close, which the client may see at once
                with self._lock:
                    self.refused += 1
                conn.close()
                continue
            t = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            t.start()
            self._threads.append(t)

    def _serve(self, conn: socket.socket) -> None:
        buf = bytearray()
        next_send = time.monotonic()
        try:
            while not self._halt.is_set():
                now = time.monotonic()
                if now >= next_send:
                    conn.sendall(self._telegram())
                    next_send = max(next_send + self._cycle, now)
                ready, _, _ = select.select([conn], [], [], max(0.0, next_send - now))
                if not ready:
                    continue
                data = conn.recv(4096)
                if not data:
                    break
                buf += data
                while (end := buf.find(_END)) >= 0:
                    self._handle(bytes(buf[: end + len(_END)]))
                    del buf[: end + len(_END)]
                if len(buf) > BUFFSIZE:
                    break
        except OSError:
            pass  # the client reset the connection: it ends, as any other end does
        finally:
            conn.close()
            with self._lock:
                self._client = None
