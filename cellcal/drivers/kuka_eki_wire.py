"""cellcal's EthernetKRL telegrams (XML over TCP) — no sockets.

EthernetKRL (a KUKA option) exchanges XML with an external system as the XML
configuration on the controller declares it; cellcal ships that configuration and the
KRL beside it (``cellcal export robot-program --driver kuka-eki``), so the telegrams are
cellcal's own, documented in docs/robots.md:

* the controller sends a state telegram every cycle of its timer interrupt (50 ms):
  ``<CellCal><State Seq="7" Ack="7" Mode="#AUT" Drives="1" EStop="0" GuardStop="0"
  InMotion="0" RobStopped="1" Program="#P_ACTIVE" StopMess="0"/><Axis A1="…" …
  A6="…"/></CellCal>`` — ``Seq``/``Ack`` the last request received and acknowledged,
  the status bits of KSS, and the measured axis angles (degrees, ``$AXIS_ACT_MEAS``);
* cellcal sends a move ``<CellCal><Cmd Seq="8" Speed="25" A1="…" … A6="…"/></CellCal>``
  or a stop ``<CellCal><Stop Seq="9"/></CellCal>``.

A flag is ``0``/``1`` or ``TRUE``/``FALSE`` (how EthernetKRL writes a BOOL was not
verified on a controller: both are taken). Telegrams are parsed strictly (every
attribute there, each a number of its kind; no DOCTYPE or entity, which a robot never
sends): anything else is one line naming what was wrong (:class:`EkiTelegramError`).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from cellcal.errors import CellcalError

ROOT = "CellCal"
START = b"<CellCal>"
END = b"</CellCal>"
MAX_TELEGRAM = 4096
AXES = ("A1", "A2", "A3", "A4", "A5", "A6")
_INT = re.compile(r"[-+]?\d+")
_REAL = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_ENUM = re.compile(r"#[A-Z_][A-Z0-9_]*")


class EkiTelegramError(CellcalError):
    """Bytes that are not one of cellcal's EthernetKRL telegrams."""


@dataclass(frozen=True)
class EkiState:
    """One state telegram."""

    seq: int
    ack: int
    mode: str
    drives: bool
    estop: bool
    guard_stop: bool
    in_motion: bool
    rob_stopped: bool
    program: str
    stop_message: bool
    axes_deg: tuple[float, ...]


def split_telegrams(buffer: bytes) -> tuple[list[bytes], bytes]:
    """The whole telegrams at the start of ``buffer`` and what is left after them."""
    out = []
    while (end := buffer.find(END)) >= 0:
        out.append(buffer[: end + len(END)])
        buffer = buffer[end + len(END) :]
    head = buffer.lstrip()[: len(START)]
    if head and not START.startswith(head):
        raise EkiTelegramError(f"bytes that do not start a <CellCal> telegram: {buffer[:40]!r}")
    if len(buffer) > MAX_TELEGRAM:
        raise EkiTelegramError(f"{len(buffer)} bytes without {END.decode()}: {buffer[:40]!r}…")
    return out, buffer


def _element(raw: bytes) -> ET.Element:
    text = raw.strip()
    if len(text) > MAX_TELEGRAM:
        raise EkiTelegramError(f"a telegram of {len(text)} bytes (at most {MAX_TELEGRAM})")
    if b"<!" in text:
        raise EkiTelegramError("a DOCTYPE, entity or comment in a telegram")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise EkiTelegramError(f"not XML ({exc}): {text[:60]!r}") from None
    if root.tag != ROOT:
        raise EkiTelegramError(f"root <{root.tag}>, not <{ROOT}>")
    return root


def _attr(el: ET.Element, name: str) -> str:
    value = el.get(name)
    if value is None:
        raise EkiTelegramError(f"<{el.tag}> without {name}")
    return value.strip()


def _int(el: ET.Element, name: str) -> int:
    value = _attr(el, name)
    if not _INT.fullmatch(value):
        raise EkiTelegramError(f"<{el.tag}> {name}={value[:20]!r}: not an integer")
    return int(value)


def _flag(el: ET.Element, name: str) -> bool:
    value = _attr(el, name).upper()
    if value not in ("0", "1", "TRUE", "FALSE"):
        raise EkiTelegramError(f"<{el.tag}> {name}={value[:20]!r}: not 0, 1, TRUE or FALSE")
    return value in ("1", "TRUE")


def _real(el: ET.Element, name: str) -> float:
    value = _attr(el, name)
    if not _REAL.fullmatch(value) or not math.isfinite(float(value)):
        raise EkiTelegramError(f"<{el.tag}> {name}={value[:20]!r}: not a finite number")
    return float(value)


def _enum(el: ET.Element, name: str) -> str:
    value = _attr(el, name).upper()
    if not _ENUM.fullmatch(value):
        raise EkiTelegramError(f"<{el.tag}> {name}={value[:20]!r}: not a KRL #VALUE")
    return value


def _child(root: ET.Element, tag: str) -> ET.Element:
    found = root.findall(tag)
    if len(found) != 1:
        raise EkiTelegramError(f"{len(found)} <{tag}> in a telegram, not one")
    return found[0]


def parse_state(raw: bytes) -> EkiState:
    root = _element(raw)
    s, a = _child(root, "State"), _child(root, "Axis")
    return EkiState(
        seq=_int(s, "Seq"),
        ack=_int(s, "Ack"),
        mode=_enum(s, "Mode"),
        drives=_flag(s, "Drives"),
        estop=_flag(s, "EStop"),
        guard_stop=_flag(s, "GuardStop"),
        in_motion=_flag(s, "InMotion"),
        rob_stopped=_flag(s, "RobStopped"),
        program=_enum(s, "Program"),
        stop_message=_flag(s, "StopMess"),
        axes_deg=tuple(_real(a, axis) for axis in AXES),
    )


def format_state(state: EkiState) -> bytes:
    def b(v: bool) -> str:
        return "1" if v else "0"

    axes = " ".join(f'{n}="{v:.6f}"' for n, v in zip(AXES, state.axes_deg, strict=True))
    return (
        f'<{ROOT}><State Seq="{state.seq}" Ack="{state.ack}" Mode="{state.mode}" '
        f'Drives="{b(state.drives)}" EStop="{b(state.estop)}" '
        f'GuardStop="{b(state.guard_stop)}" InMotion="{b(state.in_motion)}" '
        f'RobStopped="{b(state.rob_stopped)}" Program="{state.program}" '
        f'StopMess="{b(state.stop_message)}"/><Axis {axes}/></{ROOT}>'
    ).encode("ascii")


def format_move(seq: int, speed_pct: int, target_deg: list[float]) -> bytes:
    axes = " ".join(f'{n}="{v:.6f}"' for n, v in zip(AXES, target_deg, strict=True))
    return f'<{ROOT}><Cmd Seq="{seq}" Speed="{speed_pct}" {axes}/></{ROOT}>'.encode("ascii")


def format_stop(seq: int) -> bytes:
    return f'<{ROOT}><Stop Seq="{seq}"/></{ROOT}>'.encode("ascii")


@dataclass(frozen=True)
class EkiCommand:
    """A move (``target_deg`` and ``speed``) or a stop (``target_deg`` None)."""

    seq: int
    speed: int = 0
    target_deg: tuple[float, ...] | None = None


def parse_command(raw: bytes) -> EkiCommand:
    """A telegram cellcal sends (for the twin)."""
    root = _element(raw)
    children = list(root)
    if len(children) != 1 or children[0].tag not in ("Cmd", "Stop"):
        raise EkiTelegramError("a command telegram holds one <Cmd> or one <Stop>")
    el = children[0]
    if el.tag == "Stop":
        return EkiCommand(_int(el, "Seq"))
    return EkiCommand(_int(el, "Seq"), _int(el, "Speed"), tuple(_real(el, a) for a in AXES))
