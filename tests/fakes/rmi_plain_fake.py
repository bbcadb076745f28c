"""A plain fake FANUC controller with the Remote Motion Interface, for tests only.

Written from docs/robots.md ("FANUC through the Remote Motion Interface") and the packet
list of FANUC's RMI manual (B-84184EN, as FANUC's open client quotes it), never from
cellcal's RMI driver or twin: a second, independent server to prove the driver against.

Two ``socketserver`` TCP servers: the connection port answers ``FRC_Connect`` with the
session port (ErrorID 2556954 while a session is up); the session port serves one client
at a time. A background thread runs the instruction queue.

Choices where the description leaves room (each a little off the simplest form):

- Integer fields go out as JSON floats (``"ErrorID":0.0``, ``"ServoReady":1.0``) and the
  answer's other keys in reverse order after the first; every answer carries an unknown
  ``"Controller":"fake"`` field.
- The status is sent in two TCP segments (split inside the object); an instruction's
  answer and the next command's answer may share a segment.
- Joint angles carry fresh noise of at most 0.0004 deg and 12 significant digits.
- ``NextSequenceID`` is sent; ``FRC_Initialize`` while RMI runs is refused (2556943).
- Motion: linear, 100 deg/s × Speed % × ``time_scale`` wall seconds per second.
- A target with ``abs(J1) > 155`` raises an alarm when the move starts:
  ``FRC_SystemFault`` with its sequence id, HOLD until ``FRC_Reset``, and
  ``FRC_ReadError`` gives ``"MOTN-017 Limit error (G:1^A:1) (fake)"``.
- ``idle_s``: a session silent that long gets ``FRC_Terminate`` and is closed.
"""

from __future__ import annotations

import contextlib
import json
import random
import socket
import socketserver
import threading
import time
from typing import Any

ALARM = "MOTN-017 Limit error (G:1^A:1) (fake)"


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True


class RmiPlainFake:
    def __init__(self, *, time_scale: float = 0.01, idle_s: float = 3600.0) -> None:
        self.time_scale = time_scale
        self.idle_s = idle_s
        self.joints = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
        self.tp_enabled = False
        self.servo_ready = True
        self.rmi = False
        self.hold = False
        self.next_id = 1
        self.alarm = ""
        self.received: list[dict[str, Any]] = []
        self.lock = threading.Lock()
        self.session_up = threading.Event()
        self.rng = random.Random(7)
        self.queue: list[dict[str, Any]] = []
        self._servers: list[_Server] = []
        self.session_port = 0

    # ------------------------------------------------------------------ servers

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        fake = self

        class Connection(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    if not raw.strip():
                        continue
                    busy = fake.session_up.is_set()
                    fake._send(self.wfile, {
                        "Communication": "FRC_Connect",
                        "ErrorID": 2556954 if busy else 0,
                        "PortNumber": fake.session_port,
                        "MajorVersion": 3, "MinorVersion": 9,
                    })  # fmt: skip

        class Session(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                if fake.session_up.is_set():
                    return  # one client: closed at once
                fake.session_up.set()
                try:
                    fake._serve(self.request)
                finally:
                    with fake.lock:
                        fake.rmi = False
                        fake.queue.clear()
                    fake.session_up.clear()

        session = _Server((host, 0), Session)
        self.session_port = session.server_address[1]
        connection = _Server((host, port), Connection)
        self._servers = [session, connection]
        for s in self._servers:
            threading.Thread(target=s.serve_forever, args=(0.05,), daemon=True).start()
        return host, connection.server_address[1]

    def stop(self) -> None:
        for s in self._servers:
            s.shutdown()
            s.server_close()

    # ------------------------------------------------------------------ a session

    def _serve(self, sock: socket.socket) -> None:
        sock.settimeout(0.01)
        buffer = b""
        last = time.monotonic()
        running: dict[str, Any] | None = None
        while True:
            now = time.monotonic()
            if now - last > self.idle_s:
                self._send_sock(sock, {"Communication": "FRC_Terminate"})
                return
            running = self._run(sock, running)
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            last = time.monotonic()
            buffer += data
            while b"\r\n" in buffer:
                line, buffer = buffer.split(b"\r\n", 1)
                if not line.strip():
                    continue
                packet = json.loads(line)
                self.received.append(packet)
                if packet.get("Communication") == "FRC_Disconnect":
                    self._send_sock(sock, {"Communication": "FRC_Disconnect", "ErrorID": 0})
                    return
                answer = self._answer(packet)
                if answer is not None:
                    self._send_sock(sock, answer, split="Command" in answer)

    def _answer(self, p: dict[str, Any]) -> dict[str, Any] | None:
        with self.lock:
            if "Instruction" in p:
                name, seq = p["Instruction"], p.get("SequenceID")
                error = 0
                if not self.rmi:
                    error = 2556937
                elif self.hold:
                    error = 2556952
                elif seq != self.next_id:
                    error = 2556957
                elif name != "FRC_JointMotionJRep":
                    error = 2556948
                if error:
                    return {"Instruction": name, "ErrorID": error, "SequenceID": seq}
                self.next_id += 1
                self.queue.append(p)
                return None
            name = p.get("Command")
            out: dict[str, Any] = {"Command": name, "ErrorID": 0}
            if name == "FRC_GetStatus":
                out.update(ServoReady=int(self.servo_ready and not self.hold),
                           TPMode=int(self.tp_enabled), RMIMotionStatus=int(self.rmi),
                           ProgramStatus=1, SingleStepMode=0, NumberUTool=1,
                           NextSequenceID=self.next_id, NumberUFrame=0, Override=100)  # fmt: skip
            elif name == "FRC_Reset":
                self.hold = False
            elif name == "FRC_Initialize":
                if self.rmi:
                    out["ErrorID"] = 2556943
                elif self.tp_enabled or not self.servo_ready:
                    out["ErrorID"] = 2556935
                else:
                    self.rmi, self.next_id = True, 1
                    out["GroupMask"] = p.get("GroupMask", 1)
            elif name == "FRC_Abort":
                if not self.rmi:
                    out["ErrorID"] = 2556937
                self.rmi = False
                self.queue.clear()
            elif name == "FRC_ReadError":
                out.update(Count=1, ErrorData=self.alarm or "No error")
            elif name == "FRC_ReadJointAngles":
                angles = {f"J{k + 1}": float(f"{v + self.rng.uniform(-4e-4, 4e-4):.12g}")
                          for k, v in enumerate(self.joints)}  # fmt: skip
                angles.update(J7=0, J8=0, J9=0)
                out.update(TimeTag=int(time.monotonic() * 1000) % 100000, JointAngle=angles,
                           Group=p.get("Group", 1))  # fmt: skip
            elif name in ("FRC_GetUFrameUTool", "FRC_SetUFrameUTool"):
                out.update(
                    UFrameNumber=p.get("UFrameNumber", 0), UToolNumber=p.get("UToolNumber", 1)
                )
            else:
                out["ErrorID"] = 2556941
            return out

    def _run(self, sock: socket.socket, running: dict[str, Any] | None) -> dict[str, Any] | None:
        """The queue: start the next move, finish the running one (answered when done)."""
        with self.lock:
            if running is None and self.queue:
                move = self.queue.pop(0)
                target = [float(move["JointAngle"][f"J{k + 1}"]) for k in range(6)]
                if abs(target[0]) > 155.0:
                    self.alarm, self.hold = ALARM, True
                    self.queue.clear()
                    fault = {"Communication": "FRC_SystemFault", "SequenceID": move["SequenceID"]}
                    self._send_sock(sock, fault)
                    return None
                travel = max(abs(a - b) for a, b in zip(target, self.joints, strict=True))
                seconds = travel / (100.0 * float(move["Speed"]) / 100.0) * self.time_scale
                running = {**move, "_target": target, "_end": time.monotonic() + seconds}
            if running is not None and time.monotonic() >= running["_end"]:
                self.joints = running["_target"]
                answer = {"Instruction": running["Instruction"], "ErrorID": 0,
                          "SequenceID": running["SequenceID"]}  # fmt: skip
                self._send_sock(sock, answer)
                return None
            return running

    # ------------------------------------------------------------------ wire

    def _encode(self, packet: dict[str, Any]) -> bytes:
        first, *rest = packet.items()
        fields = dict([first, *reversed(rest), ("Controller", "fake")])
        for key in ("ErrorID", "ServoReady", "TPMode", "RMIMotionStatus", "SequenceID"):
            if key in fields and key != next(iter(fields)) and isinstance(fields[key], int):
                fields[key] = float(fields[key])
        return (json.dumps(fields) + "\r\n").encode("ascii")

    def _send(self, wfile: Any, packet: dict[str, Any]) -> None:
        wfile.write(self._encode(packet))
        wfile.flush()

    def _send_sock(self, sock: socket.socket, packet: dict[str, Any], split: bool = False) -> None:
        data = self._encode(packet)
        with contextlib.suppress(OSError):  # the client has gone: nothing to answer
            if split:
                cut = len(data) // 2
                sock.sendall(data[:cut])
                time.sleep(0.001)
                sock.sendall(data[cut:])
            else:
                sock.sendall(data)
