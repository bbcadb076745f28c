"""A plain fake FANUC controller serving the Remote Motion Interface (RMI), for tests only.

Written from ``docs/robots.md`` ("FANUC through the Remote Motion Interface") and the packet
list of FANUC's RMI operator's manual B-84184EN as FANUC's open client quotes it
(``FANUC-CORPORATION/fanuc_driver``: ``fanuc_libs/rmi/include/rmi/packets.hpp``, the ErrorID
list of ``fanuc_libs/rmi/src/rmi.cpp``) alone, never from cellcal's own RMI driver or twin: a
second, independent controller to prove the driver against.

Structure: two ``socketserver.ThreadingTCPServer`` s (one thread per connection, blocking
``readline``), the connection port and the session port, both ephemeral; one thread per
session writes its answers, one watches its silence; one thread is ``RMI_MOVE``, executing
accepted instructions one after another. Every line received on either port is recorded in
``received`` (parsed; a line that is not a JSON object as ``{"<raw>": text}``), every piece
written on the session port in ``segments``.

What it serves: ``FRC_Connect`` on the connection port (``ErrorID``, ``PortNumber`` of the
session port, ``MajorVersion``, ``MinorVersion``; ErrorID 2556954 while a session is up or
granted); on the session port one client at a time, the commands ``FRC_GetStatus``,
``FRC_Reset``, ``FRC_Initialize``, ``FRC_Abort``, ``FRC_ReadError``, ``FRC_ReadJointAngles``,
``FRC_GetUFrameUTool``, ``FRC_SetUFrameUTool``, ``FRC_SetOverRide`` (others: 2556941), the
communication ``FRC_Disconnect`` and the instruction ``FRC_JointMotionJRep`` (others: 2556948),
answered when the robot stands at its target. Fault switches: ``tp_enabled``, ``servo_off``,
``single_step``, ``raise_alarm(text)`` (the next move stops halfway: ``FRC_SystemFault`` with
its sequence id, RMI in HOLD and the servo off until ``FRC_Reset`` or ``reset_on_pendant()``,
the text in ``FRC_ReadError``), ``idle_timeout_s`` (``FRC_Terminate``, then the session is
closed).

Choices where the published description leaves room (several deliberately off the obvious):

- Integer fields (ErrorID, ServoReady, TPMode, PortNumber, SequenceID, TimeTag, ...) are
  written as integral floats: ``0.0``, ``16002.0``. Real fields with an integral value are
  written bare (``"J7": 0``); others with all of Python's digits (``repr``), so an angle near
  zero comes in exponent form (``-3.1e-06``).
- The measured joint angles carry fresh uniform noise of at most 4e-6 deg (fixed seed);
  ``q_deg()`` is noise-free. J7..J9 are 0.
- After the first key, keys come in the reverse of the manual's order (also inside
  ``JointAngle``: J9 first), with an unknown key ``"Tick"`` (a packet counter) among them;
  ``", "`` and ``": "`` separate them. Each answer ends ``\\r\\n``.
- The session's writer sends what is pending in pieces of 7..90 bytes (fixed seed) every
  ``cycle_s``: an answer longer than a piece is split across segments, and the end of one
  answer shares a segment with the next when both are pending (a piece never ends between
  two pending packets). The ``FRC_Connect`` answer is sent in two pieces.
- ``fault_answer`` (default None): an alarm is then also answered as the stopped
  instruction's answer with this ErrorID, right after ``FRC_SystemFault`` and in the same
  segment as its end.
- The session port is granted by ``FRC_Connect`` for ``claim_s``; a connection to it without
  a grant, or while a session is up, is closed at once (counted in ``refused``). A session
  that ended is freed only ``release_s`` later (``FRC_Connect`` answers 2556954 until then).
- RMI outlives a session: what a session started keeps running and its answers are dropped;
  the next session sees ``RMIMotionStatus`` 1 and must ``FRC_Abort`` before
  ``FRC_Initialize``, which answers 2556943 while RMI runs.
- Status: ``RMIMotionStatus`` 0 not running, 1 running, 2 in HOLD; ``ProgramStatus`` 0
  aborted, 2 running, 1 paused (HOLD); ``ServoReady`` 0 while ``servo_off`` or an alarm is
  active; ``TPMode`` 1 while ``tp_enabled``. ``NextSequenceID`` is always sent.
- Instructions are checked on arrival, in this order: known instruction (2556948), RMI
  running (2556937), not in HOLD (2556952), teach pendant (2556934), servo (2556935), the
  next consecutive sequence id (2556957), six finite joint angles (2556951), ``SpeedType``
  ``Percent`` (2556958) and ``Speed`` an integer 1..100 (2556959), ``TermType`` ``FINE`` or
  ``CNT`` (2556960), ``TermValue`` 0..100 if given (2556961). A refusal does not use up the
  sequence id, and neither does the instruction an alarm stopped: after the reset the
  controller still expects its id (``NextSequenceID`` says so).
- Motion: all joints start and stop together on a cosine profile, lasting
  ``max |dq| / (120 deg/s * Speed/100 * Override/100) * time_scale``.
- ``FRC_Reset`` always answers 0; it clears an alarm but not ``servo_off`` (an e-stop held),
  and leaves RMI running. ``FRC_Abort`` always answers 0: the robot stops where it is, queued
  instructions are dropped unanswered, RMI ends.
- ``FRC_ReadError`` gives the most recent alarm texts (history kept after a reset; while
  ``servo_off``, ``SRVO-001 Operator panel E-stop`` first), ``""`` when there is none.
- Only motion group 1 exists: another ``Group`` is 2556967, another ``GroupMask`` 2556968.
- A line that is not a JSON object with a known first key is answered with ``Command``
  ``Unknown`` and ErrorID 2556941; a line over 64 KiB without an end ends the connection.
"""

from __future__ import annotations

import contextlib
import json
import math
import random
import socket
import socketserver
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

JOINTS = tuple(f"J{i}" for i in range(1, 10))
MAX_JOINT_SPEED = 120.0  # deg/s at Speed 100 and Override 100
NOISE = 4e-6  # deg
MAX_LINE = 65536
VERSION = (3, 7)

E_UTOOL = 2556930
E_UFRAME = 2556931
E_OVERRIDE = 2556933
E_CANNOT_EXECUTE = 2556934
E_SERVO_OFF = 2556935
E_NOT_RUNNING = 2556937
E_INVALID_COMMAND = 2556941
E_CONTROLLER_STATE = 2556943
E_INVALID_INSTRUCTION = 2556948
E_VALUE = 2556949
E_POSITION = 2556951
E_HOLD = 2556952
E_CONNECTED = 2556954
E_SEQUENCE = 2556957
E_SPEED_TYPE = 2556958
E_SPEED = 2556959
E_TERM_TYPE = 2556960
E_TERM_VALUE = 2556961
E_GROUP = 2556967
E_GROUP_MASK = 2556968
E_SINGLE_STEP = 2556971

ESTOP_TEXT = "SRVO-001 Operator panel E-stop"


def encode(packet: dict[str, Any]) -> bytes:
    """One packet as the fake writes it (see the module docstring), ``\\r\\n`` included."""
    return (_text(packet) + "\r\n").encode("utf-8")


def _text(value: Any) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)}: {_text(v)}" for k, v in value.items()) + "}"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, bool):
        raise TypeError("no booleans in RMI packets")
    if isinstance(value, int):
        return f"{value}.0"
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a JSON number: {value!r}")
        return str(int(value)) if value.is_integer() else repr(value)
    raise TypeError(f"cannot write {type(value).__name__}")


def _as_int(value: Any) -> int | None:
    """An integer field of a request: an int, or an integral float; None otherwise."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _as_real(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    v = float(value)
    return v if math.isfinite(v) else None


class _Session:
    """One client on the session port: its outbox, written by its own thread."""

    def __init__(self, sock: socket.socket, seed: int) -> None:
        self.sock = sock
        self.cond = threading.Condition()
        self.out = bytearray()
        self.closing = False  # shut the connection once the outbox is written
        self.dead = False
        self.last_rx = time.monotonic()
        self.rng = random.Random(seed)

    def send(self, data: bytes) -> None:
        with self.cond:
            if not self.dead and not self.closing:
                self.out += data
                self.cond.notify_all()

    def close_after_flush(self) -> None:
        with self.cond:
            self.closing = True
            self.cond.notify_all()

    def kill(self) -> None:
        with self.cond:
            self.dead = True
            self.cond.notify_all()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = False
    block_on_close = True

    def __init__(self, address: tuple[str, int], handler: type, fake: RmiFake) -> None:
        self.fake = fake
        super().__init__(address, handler)


class _ConnectionHandler(socketserver.StreamRequestHandler):
    server: _Server

    def handle(self) -> None:
        fake = self.server.fake
        sock: socket.socket = self.request
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        fake._track(sock, True)
        try:
            while not fake._halt.is_set():
                line = self.rfile.readline(MAX_LINE)
                if not line.endswith(b"\n"):
                    return
                packet = fake._parse(line)
                if packet is None:
                    continue
                data = encode(fake._on_connection_packet(packet))
                cut = len(data) // 3
                sock.sendall(data[:cut])
                time.sleep(fake.cycle_s)
                sock.sendall(data[cut:])
        except OSError:
            return
        finally:
            fake._track(sock, False)


class _SessionHandler(socketserver.StreamRequestHandler):
    server: _Server

    def handle(self) -> None:
        fake = self.server.fake
        sock: socket.socket = self.request
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        session = fake._open_session(sock)
        if session is None:
            return
        helpers = [
            threading.Thread(target=fake._write_loop, args=(session,), name="rmi-fake-writer"),
            threading.Thread(target=fake._idle_loop, args=(session,), name="rmi-fake-idle"),
        ]
        for t in helpers:
            t.start()
        try:
            while not fake._halt.is_set():
                line = self.rfile.readline(MAX_LINE)
                if not line.endswith(b"\n"):
                    return
                session.last_rx = time.monotonic()
                packet = fake._parse(line)
                if packet is not None:
                    fake._on_session_packet(session, packet)
        except OSError:
            return
        finally:
            fake._end_session(session)
            for t in helpers:
                t.join()


class RmiFake:
    """The controller; see the module docstring. ``start`` then ``stop``."""

    def __init__(
        self,
        q0_deg: Sequence[float] = (0.0, -20.0, 15.0, 0.0, -45.0, 0.0),
        *,
        time_scale: float = 1.0,
        idle_timeout_s: float = 3600.0,
        release_s: float = 0.2,
        claim_s: float = 3.0,
        cycle_s: float = 0.001,
        override: int = 100,
        fault_answer: int | None = None,
        uframe: int = 0,
        utool: int = 1,
    ) -> None:
        if len(q0_deg) != 6:
            raise ValueError("q0_deg: 6 joint angles")
        self.time_scale = float(time_scale)
        self.idle_timeout_s = float(idle_timeout_s)
        self.release_s = float(release_s)
        self.claim_s = float(claim_s)
        self.cycle_s = float(cycle_s)
        self.override = int(override)
        self.fault_answer = fault_answer
        # fault switches
        self.tp_enabled = False
        self.servo_off = False
        self.single_step = False
        # what happened
        self.received: list[dict[str, Any]] = []
        self.segments: list[bytes] = []
        self.sessions = 0
        self.refused = 0
        self.connect_refusals = 0
        self.terminated = 0
        self._uframe, self._utool = int(uframe), int(utool)
        self._q = [float(v) for v in q0_deg]
        self._running = False
        self._alarm: str | None = None  # active alarm: HOLD, servo off
        self._armed: str | None = None  # the alarm the next move raises
        self._history: list[str] = []  # alarm texts, most recent first
        self._next_seq = 1
        self._queue: deque[tuple[int, list[float], int, _Session]] = deque()
        self._gen = 0  # bumped by FRC_Abort: the move under way stops
        self._moving = False
        self._tick = 0
        self._t0 = time.monotonic()
        self._rng = random.Random(1982)
        self._lock = threading.Condition()
        self._halt = threading.Event()
        self._session: _Session | None = None
        self._grant_until = 0.0
        self._free_at = 0.0
        self._live: set[socket.socket] = set()
        self._servers: list[_Server] = []
        self._threads: list[threading.Thread] = []

    # -- public ----------------------------------------------------------------------------

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        """Listen on ``host:port`` (connection) and an ephemeral session port of ``host``."""
        connection = _Server((host, port), _ConnectionHandler, self)
        session = _Server((host, 0), _SessionHandler, self)
        self._servers = [connection, session]
        for server in self._servers:
            t = threading.Thread(
                target=server.serve_forever, kwargs={"poll_interval": 0.05}, name="rmi-fake"
            )
            t.start()
            self._threads.append(t)
        program = threading.Thread(target=self._program_loop, name="rmi-fake-RMI_MOVE")
        program.start()
        self._threads.append(program)
        addr = connection.server_address
        return str(addr[0]), int(addr[1])

    def stop(self) -> None:
        self._halt.set()
        with self._lock:
            self._lock.notify_all()
            session = self._session
            live = list(self._live)
        for server in self._servers:
            server.shutdown()
        if session is not None:
            session.kill()
        for sock in live:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        for server in self._servers:
            server.server_close()  # joins the connection threads
        for t in self._threads:
            t.join(timeout=5.0)

    @property
    def session_port(self) -> int:
        return int(self._servers[1].server_address[1])

    @property
    def session_up(self) -> bool:
        """A client holds the session port, or it was granted, or was freed too recently."""
        with self._lock:
            return self._busy(time.monotonic())

    @property
    def rmi_running(self) -> bool:
        with self._lock:
            return self._running

    @property
    def alarm(self) -> str | None:
        with self._lock:
            return self._alarm

    def raise_alarm(self, text: str) -> None:
        """The next move stops halfway with this alarm."""
        with self._lock:
            self._armed = text

    def reset_on_pendant(self) -> None:
        """The operator resets the alarm on the pendant (as ``FRC_Reset`` does)."""
        with self._lock:
            self._alarm = None

    def q_deg(self) -> list[float]:
        with self._lock:
            return list(self._q)

    def packets(self, name: str) -> list[dict[str, Any]]:
        """The received packets whose first value is ``name`` (``FRC_Abort``, ...)."""
        with self._lock:
            return [p for p in self.received if next(iter(p.values()), None) == name]

    def sequence_ids(self) -> list[Any]:
        """The SequenceID of every ``FRC_JointMotionJRep`` received, as sent."""
        return [p.get("SequenceID") for p in self.packets("FRC_JointMotionJRep")]

    # -- writing ---------------------------------------------------------------------------

    def _answer(self, key: str, name: str, *fields: tuple[str, Any]) -> dict[str, Any]:
        """First key, then the fields in reverse order with ``Tick`` after the first."""
        with self._lock:
            self._tick += 1
            tick = self._tick
        rest = list(reversed(fields))
        rest.insert(min(1, len(rest)), ("Tick", tick))
        return {key: name, **dict(rest)}

    def _write_loop(self, s: _Session) -> None:
        while True:
            with s.cond:
                while not s.out and not s.closing and not s.dead:
                    s.cond.wait()
                if s.dead or not s.out:
                    break
                n = s.rng.randint(7, 90)
                if n < len(s.out) and s.out[n - 2 : n] == b"\r\n":
                    n += 5  # never cut between two pending packets: they share a segment
                chunk = bytes(s.out[:n])
                del s.out[:n]
            try:
                s.sock.sendall(chunk)
            except OSError:
                break
            with self._lock:
                self.segments.append(chunk)
            time.sleep(self.cycle_s)
        with contextlib.suppress(OSError):
            s.sock.shutdown(socket.SHUT_RDWR)

    def _idle_loop(self, s: _Session) -> None:
        while not self._halt.is_set():
            with s.cond:
                if s.dead or s.closing:
                    return
            left = s.last_rx + self.idle_timeout_s - time.monotonic()
            if left <= 0:
                with self._lock:
                    self.terminated += 1
                s.send(encode({"Communication": "FRC_Terminate"}))
                s.close_after_flush()
                return
            self._halt.wait(min(left, 0.02))

    # -- reading ---------------------------------------------------------------------------

    def _parse(self, line: bytes) -> dict[str, Any] | None:
        text = line.decode("utf-8", "replace").strip()
        if not text:
            return None
        try:
            packet = json.loads(text)
        except ValueError:
            packet = None
        if not isinstance(packet, dict) or not packet:
            packet = {"<raw>": text}
        with self._lock:
            self.received.append(packet)
        return packet

    def _track(self, sock: socket.socket, live: bool) -> None:
        with self._lock:
            if live:
                self._live.add(sock)
            else:
                self._live.discard(sock)

    # -- the connection port ---------------------------------------------------------------

    def _busy(self, now: float) -> bool:
        return self._session is not None or now < self._grant_until or now < self._free_at

    def _on_connection_packet(self, packet: dict[str, Any]) -> dict[str, Any]:
        if packet.get("Communication") != "FRC_Connect" or next(iter(packet)) != "Communication":
            return self._answer("Command", "Unknown", ("ErrorID", E_INVALID_COMMAND))
        now = time.monotonic()
        with self._lock:
            busy = self._busy(now)
            if busy:
                self.connect_refusals += 1
            else:
                self._grant_until = now + self.claim_s
        return self._answer(
            "Communication",
            "FRC_Connect",
            ("ErrorID", E_CONNECTED if busy else 0),
            ("PortNumber", 0 if busy else self.session_port),
            ("MajorVersion", VERSION[0]),
            ("MinorVersion", VERSION[1]),
        )

    # -- the session port ------------------------------------------------------------------

    def _open_session(self, sock: socket.socket) -> _Session | None:
        with self._lock:
            now = time.monotonic()
            if self._halt.is_set() or self._session is not None or now >= self._grant_until:
                self.refused += 1
                return None
            self._grant_until = 0.0
            self.sessions += 1
            self._session = _Session(sock, seed=self.sessions)
            return self._session

    def _end_session(self, s: _Session) -> None:
        s.kill()
        with self._lock:
            if self._session is s:
                self._session = None
                self._free_at = time.monotonic() + self.release_s

    def _on_session_packet(self, s: _Session, packet: dict[str, Any]) -> None:
        key, name = next(iter(packet.items()))
        if key == "Communication" and name == "FRC_Disconnect":
            s.send(encode(self._answer("Communication", "FRC_Disconnect", ("ErrorID", 0))))
            s.close_after_flush()
        elif key == "Command" and isinstance(name, str):
            s.send(encode(self._command(name, packet)))
        elif key == "Instruction" and isinstance(name, str):
            answer = self._instruction(name, packet, s)
            if answer is not None:
                s.send(encode(answer))
        else:
            s.send(encode(self._answer("Command", "Unknown", ("ErrorID", E_INVALID_COMMAND))))

    def _status(self) -> tuple[int, int]:
        """(RMIMotionStatus, ProgramStatus) now."""
        if not self._running:
            return 0, 0
        return (2, 1) if self._alarm is not None else (1, 2)

    def _group_ok(self, packet: dict[str, Any]) -> bool:
        return "Group" not in packet or _as_int(packet["Group"]) == 1

    def _command(self, name: str, p: dict[str, Any]) -> dict[str, Any]:
        def done(error: int, *fields: tuple[str, Any]) -> dict[str, Any]:
            return self._answer("Command", name, ("ErrorID", error), *fields)

        fields: tuple[tuple[str, Any], ...]
        with self._lock:
            if name == "FRC_GetStatus":
                motion, program = self._status()
                servo = 0 if self.servo_off or self._alarm is not None else 1
                fields = (
                    ("ServoReady", servo),
                    ("TPMode", 1 if self.tp_enabled else 0),
                    ("RMIMotionStatus", motion),
                    ("ProgramStatus", program),
                    ("SingleStepMode", 1 if self.single_step else 0),
                    ("NumberUTool", self._utool),
                    ("NextSequenceID", self._next_seq),
                    ("NumberUFrame", self._uframe),
                    ("Override", self.override),
                )
            elif name == "FRC_Reset":
                self._alarm = None
                fields = ()
            elif name == "FRC_Abort":
                self._gen += 1
                self._queue.clear()
                self._running = False
                self._lock.notify_all()
                fields = ()
            elif name == "FRC_Initialize":
                mask = _as_int(p.get("GroupMask", 1))
                if mask != 1:
                    return done(E_GROUP_MASK)
                if self.tp_enabled:
                    return done(E_CANNOT_EXECUTE)
                if self.single_step:
                    return done(E_SINGLE_STEP)
                if self.servo_off or self._alarm is not None:
                    return done(E_SERVO_OFF)
                if self._running:
                    return done(E_CONTROLLER_STATE)
                self._running, self._next_seq = True, 1
                fields = (("GroupMask", 1),)
            elif name == "FRC_ReadError":
                count = _as_int(p.get("Count", 1))
                if count is None or not 1 <= count <= 5:
                    return done(E_VALUE)
                texts = ([ESTOP_TEXT] if self.servo_off else []) + self._history
                texts = (texts + [""] * count)[:count]
                data = [(f"ErrorData{i + 1 if i else ''}", t) for i, t in enumerate(texts)]
                fields = ((("Count", count),) if "Count" in p else ()) + tuple(data)
            elif name == "FRC_ReadJointAngles":
                if not self._group_ok(p):
                    return done(E_GROUP)
                q = [v + self._rng.uniform(-NOISE, NOISE) for v in self._q] + [0.0] * 3
                angles = {k: q[i] for i, k in reversed(list(enumerate(JOINTS)))}
                tag = int((time.monotonic() - self._t0) * 1000)
                fields = (("TimeTag", tag), ("JointAngle", angles), ("Group", 1))
            elif name == "FRC_GetUFrameUTool":
                if not self._group_ok(p):
                    return done(E_GROUP)
                fields = (
                    ("UFrameNumber", self._uframe),
                    ("UToolNumber", self._utool),
                    ("Group", 1),
                )
            elif name == "FRC_SetUFrameUTool":
                if not self._group_ok(p):
                    return done(E_GROUP)
                uframe, utool = _as_int(p.get("UFrameNumber")), _as_int(p.get("UToolNumber"))
                if uframe is None or not 0 <= uframe <= 9:
                    return done(E_UFRAME)
                if utool is None or not 1 <= utool <= 10:
                    return done(E_UTOOL)
                self._uframe, self._utool = uframe, utool
                fields = (("Group", 1),) if "Group" in p else ()
            elif name == "FRC_SetOverRide":
                value = _as_int(p.get("Value"))
                if value is None or not 1 <= value <= 100:
                    return done(E_OVERRIDE)
                self.override = value
                fields = ()
            else:
                return done(E_INVALID_COMMAND)
        return done(0, *fields)

    def _instruction(self, name: str, p: dict[str, Any], s: _Session) -> dict[str, Any] | None:
        seq_field = p.get("SequenceID")
        seq = _as_int(seq_field)

        def refuse(error: int) -> dict[str, Any]:
            return self._answer(
                "Instruction", name, ("ErrorID", error), ("SequenceID", seq if seq else 0)
            )

        if name != "FRC_JointMotionJRep":
            return refuse(E_INVALID_INSTRUCTION)
        with self._lock:
            if not self._running:
                return refuse(E_NOT_RUNNING)
            if self._alarm is not None:
                return refuse(E_HOLD)
            if self.tp_enabled:
                return refuse(E_CANNOT_EXECUTE)
            if self.servo_off:
                return refuse(E_SERVO_OFF)
            if seq != self._next_seq:
                return refuse(E_SEQUENCE)
            angles = p.get("JointAngle")
            target = (
                [_as_real(angles.get(k)) for k in JOINTS[:6]] if isinstance(angles, dict) else []
            )
            if len(target) != 6 or any(v is None for v in target):
                return refuse(E_POSITION)
            if p.get("SpeedType") != "Percent":
                return refuse(E_SPEED_TYPE)
            speed = _as_int(p.get("Speed"))
            if speed is None or not 1 <= speed <= 100:
                return refuse(E_SPEED)
            if p.get("TermType") not in ("FINE", "CNT"):
                return refuse(E_TERM_TYPE)
            term = _as_int(p.get("TermValue", 0))
            if term is None or not 0 <= term <= 100:
                return refuse(E_TERM_VALUE)
            self._next_seq += 1
            self._queue.append((seq, [float(v or 0.0) for v in target], speed, s))
            self._lock.notify_all()
        return None

    # -- RMI_MOVE --------------------------------------------------------------------------

    def _program_loop(self) -> None:
        while not self._halt.is_set():
            with self._lock:
                if not self._queue:
                    self._lock.wait(0.05)
                    continue
                seq, target, speed, session = self._queue.popleft()
                start, gen = list(self._q), self._gen
                alarm, self._armed = self._armed, None
                rate = MAX_JOINT_SPEED * speed / 100.0 * self.override / 100.0
            travel = max(abs(b - a) for a, b in zip(start, target, strict=True))
            duration = travel / rate * self.time_scale
            stop_at = 0.5 if alarm is not None else 1.0
            t0 = time.monotonic()
            while True:
                with self._lock:
                    if self._halt.is_set() or gen != self._gen:
                        self._moving = False
                        break
                    elapsed = time.monotonic() - t0
                    s = min(stop_at, 1.0 if duration <= 0 else elapsed / duration)
                    shape = (1.0 - math.cos(math.pi * s)) / 2.0
                    self._q = [a + (b - a) * shape for a, b in zip(start, target, strict=True)]
                    self._moving = s < stop_at
                    if s >= stop_at:
                        if alarm is not None:
                            self._fault(seq, alarm, session)
                        else:
                            self._q = list(target)
                            done = self._answer(
                                "Instruction",
                                "FRC_JointMotionJRep",
                                ("ErrorID", 0),
                                ("SequenceID", seq),
                            )
                            session.send(encode(done))
                        break
                time.sleep(0.002)

    def _fault(self, seq: int, text: str, session: _Session) -> None:
        """The alarm stops the robot: HOLD, the queue dropped, the sequence id not used."""
        self._alarm = text
        self._history.insert(0, text)
        self._queue.clear()
        self._next_seq = seq
        data = encode({"Communication": "FRC_SystemFault", "SequenceID": seq})
        if self.fault_answer is not None:
            data += encode(
                self._answer(
                    "Instruction",
                    "FRC_JointMotionJRep",
                    ("ErrorID", self.fault_answer),
                    ("SequenceID", seq),
                )
            )
        session.send(data)
