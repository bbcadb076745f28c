"""FANUC's Remote Motion Interface on the wire (JSON lines over TCP) — no sockets.

RMI is a controller option (R912, R-30iB Plus and later): the controller listens on TCP
16001, answers ``{"Communication": "FRC_Connect"}`` with the port the session then runs
on (``PortNumber``, usually 16002) and takes one client at a time. Every packet is one
JSON object on a line ending ``\\r\\n``; a packet's kind is its first key —
``Communication`` (the session), ``Command`` (answered at once) or ``Instruction``
(queued in the controller's RMI_MOVE program, carrying consecutive ``SequenceID``s from
1 after ``FRC_Initialize``; its reply comes when it has been executed). Every reply
carries ``ErrorID`` (0: none); the controller sends ``FRC_SystemFault`` (with the
sequence id of the instruction it stopped) and, after 60 minutes without a packet,
``FRC_Terminate`` before it closes the session, unasked.

Sources: FANUC's RMI operator's manual B-84184EN as FANUC's own open client quotes it
(``FANUC-CORPORATION/fanuc_driver``, ``fanuc_libs/rmi``: packet fields and the error ids
below), the open clients ``vertec-io/Fanuc_RMI_API`` and PyPI ``fanuc-rmi``. Real
controllers' number formatting was not seen: fields are compared, never bytes; an
integer field accepts an integral float and a real field an integer.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from cellcal.errors import CellcalError

PORT = 16001
MAX_LINE = 65536  # a reply is a few hundred bytes; more without a line end is not RMI
JOINTS = tuple(f"J{k}" for k in range(1, 10))  # JointAngle always holds J1..J9

#: The controller's ErrorIDs a campaign can meet, in the manual's words (shortened).
ERRORS = {
    2556929: "internal system error",
    2556930: "invalid UTool number",
    2556931: "invalid UFrame number",
    2556933: "invalid speed override",
    2556934: "cannot execute the TP program",
    2556935: "controller servo is off",
    2556936: "cannot execute the TP program",
    2556937: "RMI is not running",
    2556940: "cannot reset the controller",
    2556941: "invalid RMI command",
    2556942: "RMI command failed",
    2556943: "invalid controller state",
    2556944: "cycle the controller's power",
    2556948: "invalid RMI instruction",
    2556949: "invalid value",
    2556951: "invalid position data",
    2556952: "RMI is in HOLD",
    2556953: "remote device disconnected",
    2556954: "the robot is already connected (one client at a time)",
    2556955: "wait for the command to be done",
    2556956: "wait for the instruction to be done",
    2556957: "invalid sequence id",
    2556958: "invalid speed type",
    2556959: "invalid speed value",
    2556960: "invalid term type",
    2556961: "invalid term value",
    2556964: "invalid destination position",
    2556967: "invalid group number",
    2556968: "invalid group mask",
    2556971: "the robot is in single step mode",
    7004: "the program is in use",
    7015: "RMI_MOVE is the selected TP program: select another one",
}


class RmiPacketError(CellcalError):
    """Bytes that are not an RMI packet, or a packet without the fields its kind has."""


def error_text(error_id: int) -> str:
    """``ErrorID 2556935 (controller servo is off)``: the id, and its meaning if known."""
    meaning = ERRORS.get(error_id)
    return f"ErrorID {error_id}" + (f" ({meaning})" if meaning else "")


def encode(packet: dict[str, Any]) -> bytes:
    """One packet as the line that carries it."""
    return (json.dumps(packet, separators=(",", ":"), allow_nan=False) + "\r\n").encode("ascii")


def split_lines(buffer: bytes) -> tuple[list[bytes], bytes]:
    """The complete lines in ``buffer`` (line end ``\\r\\n``, a bare ``\\n`` taken too;
    blank lines dropped) and what is left of an unfinished one."""
    *lines, rest = buffer.split(b"\n")
    if len(rest) > MAX_LINE:
        raise RmiPacketError(f"more than {MAX_LINE} bytes without a line end")
    return [raw.rstrip(b"\r") for raw in lines if raw.strip()], rest


def decode(line: bytes) -> dict[str, Any]:
    """One line's packet: a JSON object whose first key names its kind."""
    try:
        packet = json.loads(line.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        raise RmiPacketError(f"not a JSON line: {_shown(line)}") from None
    if not isinstance(packet, dict) or not packet:
        raise RmiPacketError(f"not a JSON object: {_shown(line)}")
    kind, name = next(iter(packet.items()))
    if kind not in ("Communication", "Command", "Instruction") or not isinstance(name, str):
        raise RmiPacketError(f"no Communication, Command or Instruction first: {_shown(line)}")
    return packet


def name_of(packet: dict[str, Any]) -> tuple[str, str]:
    """(kind, name): ``("Command", "FRC_GetStatus")``."""
    kind, name = next(iter(packet.items()))
    return str(kind), str(name)


def integer(packet: dict[str, Any], key: str) -> int:
    """An integer field (an integral float is taken: the controller's formatting is not
    known)."""
    value = packet.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RmiPacketError(f"{name_of(packet)[1]}: {key} missing or not a number")
    if not (math.isfinite(value) and value == int(value)):
        raise RmiPacketError(f"{name_of(packet)[1]}: {key} = {value!r} is not an integer")
    return int(value)


def real(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise RmiPacketError(f"{where} missing or not a finite number")
    return float(value)


# ---------------------------------------------------------------------- requests


def connect() -> dict[str, Any]:
    return {"Communication": "FRC_Connect"}


def disconnect() -> dict[str, Any]:
    return {"Communication": "FRC_Disconnect"}


def command(name: str, **fields: Any) -> dict[str, Any]:
    return {"Command": name, **fields}


def joint_motion(seq: int, joints_deg: list[float], speed_pct: int) -> dict[str, Any]:
    """``FRC_JointMotionJRep``: a joint move to absolute angles (degrees; J7..J9 0), at
    ``speed_pct`` % of the joints' maximum, ending in a FINE (exact) stop."""
    angles = {j: 0.0 for j in JOINTS}
    angles.update({f"J{k + 1}": float(v) for k, v in enumerate(joints_deg)})
    return {
        "Instruction": "FRC_JointMotionJRep",
        "SequenceID": seq,
        "JointAngle": angles,
        "SpeedType": "Percent",
        "Speed": speed_pct,
        "TermType": "FINE",
        "TermValue": 0,
    }


# ---------------------------------------------------------------------- replies


@dataclass(frozen=True)
class RmiStatus:
    """``FRC_GetStatus``'s answer: servo ready, the teach pendant enabled, RMI's motion
    program running (0: not initialised), the TP program's status, single step, the
    override (%) and the next sequence id the controller expects (None when the
    controller leaves it out)."""

    servo_ready: bool
    tp_enabled: bool
    rmi_running: bool
    program_status: int
    single_step: bool
    override: int
    next_sequence: int | None

    @property
    def text(self) -> str:
        return (
            f"ServoReady {int(self.servo_ready)}, TPMode {int(self.tp_enabled)}, "
            f"RMIMotionStatus {int(self.rmi_running)}, SingleStepMode {int(self.single_step)}, "
            f"Override {self.override}"
        )


def status_of(packet: dict[str, Any]) -> RmiStatus:
    nxt = packet.get("NextSequenceID")
    return RmiStatus(
        servo_ready=integer(packet, "ServoReady") == 1,
        tp_enabled=integer(packet, "TPMode") != 0,
        rmi_running=integer(packet, "RMIMotionStatus") != 0,
        program_status=integer(packet, "ProgramStatus"),
        single_step=integer(packet, "SingleStepMode") != 0,
        override=integer(packet, "Override") if "Override" in packet else 100,
        next_sequence=None if nxt is None else integer(packet, "NextSequenceID"),
    )


def joints_of(packet: dict[str, Any], n: int) -> list[float]:
    """The first ``n`` of ``JointAngle``'s J1..J9 (degrees)."""
    angles = packet.get("JointAngle")
    if not isinstance(angles, dict):
        raise RmiPacketError("FRC_ReadJointAngles: no JointAngle object")
    return [real(angles.get(f"J{k}"), f"FRC_ReadJointAngles: J{k}") for k in range(1, n + 1)]


def errors_of(packet: dict[str, Any]) -> str:
    """``FRC_ReadError``'s texts (ErrorData, ErrorData2..5), joined."""
    keys = ["ErrorData", *(f"ErrorData{k}" for k in range(2, 6))]
    texts = [str(packet[k]).strip() for k in keys if str(packet.get(k) or "").strip()]
    return "; ".join(texts)


def _shown(line: bytes) -> str:
    text = line[:80].decode("ascii", "replace")
    return repr(text + ("…" if len(line) > 80 else ""))
