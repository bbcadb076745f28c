"""A URDF file's text screened before anything parses it for real, and Pinocchio's
reading of it with every failure one line naming the file.

:func:`screen` is one pass of expat, bounded, that refuses what a robot's URDF never
needs and what makes a reader hang or blow up (Pinocchio's C++ reader, ElementTree):

* No DTD (``<!DOCTYPE``), hence no entity — internal (billion laughs, quadratic
  blow-up) or external (a file or URL read on our behalf) — as defusedxml refuses them.
* At most :data:`MAX_BYTES` of text, :data:`MAX_DEPTH` levels of nesting and
  :data:`MAX_ELEMENTS` elements.
* The root element is ``<robot>``, with at most :data:`MAX_JOINTS` joints and
  :data:`MAX_LINKS` links (a serial industrial arm has about a dozen of each with its
  fixed frames; a 500-joint file made Pinocchio allocate gigabytes).
* No ``<mimic>`` joint: cellcal's joints turn by their own readings.

Each refusal is one :class:`~cellcal.errors.FileFormatError` naming the file and the
bound. :func:`pinocchio_model` then builds Pinocchio's model of the text: whatever it
raises (any std::exception Boost.Python translates, bad_alloc as MemoryError) and the
first complaint its parser writes on the process's stderr become one line.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import xml.parsers.expat as expat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from cellcal.errors import FileFormatError

#: A robot's URDF (with comments, Gazebo and transmission tags) is tens of kB.
MAX_BYTES = 4 * 1024 * 1024
MAX_DEPTH = 64
MAX_ELEMENTS = 100_000
MAX_JOINTS = 64
MAX_LINKS = 65


class _RefusedError(Exception):
    """Raised inside expat's handlers to stop the parse."""


def screen(text: str, path: Path) -> None:
    """Refuse (one line naming ``path``) a URDF text that breaks the module's rules."""
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_BYTES:
        raise FileFormatError(
            f"{path}: {size / 1e6:.1f} MB is too large for a robot's URDF "
            f"(at most {MAX_BYTES / 1e6:.0f} MB)"
        )
    depth = 0
    elements = 0
    counts = {"joint": 0, "link": 0}
    parser = expat.ParserCreate()

    def refuse(*_: object) -> None:
        raise _RefusedError(
            "a DTD or entity declaration (<!DOCTYPE …>, <!ENTITY …>): a URDF needs none, "
            "and they are refused (entity expansion, external files)"
        )

    def start(name: str, _attrs: dict[str, str]) -> None:
        nonlocal depth, elements
        depth += 1
        elements += 1
        if depth == 1 and name != "robot":
            raise _RefusedError(f"not a URDF (its root element is <{name}>, not <robot>)")
        if depth > MAX_DEPTH:
            raise _RefusedError(f"nested more than {MAX_DEPTH} levels deep: not a robot's URDF")
        if elements > MAX_ELEMENTS:
            raise _RefusedError(f"more than {MAX_ELEMENTS} elements: not a robot's URDF")
        if depth == 2 and name in counts:
            counts[name] += 1
            bound = MAX_JOINTS if name == "joint" else MAX_LINKS
            if counts[name] > bound:
                raise _RefusedError(
                    f"more than {bound} <{name}> elements: at most {bound} (a serial "
                    "industrial arm has about a dozen)"
                )
        if depth == 3 and name == "mimic":
            raise _RefusedError(
                "a <mimic> joint: cellcal's joints turn by their own readings (a coupled "
                "joint is a model TOML's couple = { joint = J, factor = F })"
            )

    def end(_name: str) -> None:
        nonlocal depth
        depth -= 1

    def external(*_: object) -> int:
        refuse()
        return 0

    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = external
    parser.StartElementHandler = start
    parser.EndElementHandler = end
    try:
        parser.Parse(text, True)
    except _RefusedError as exc:
        raise FileFormatError(f"{path}: {exc}") from None
    except expat.ExpatError as exc:
        raise FileFormatError(
            f"{path}: not XML ({expat.ErrorString(exc.code)}, line {exc.lineno})"
        ) from None
    except RecursionError:
        raise FileFormatError(f"{path}: nested too deeply to be a URDF") from None


@contextlib.contextmanager
def _c_stderr() -> Iterator[Callable[[], list[str]]]:
    """The C++ parser writes its complaints to the process's stderr: hold them, so that
    a bad file is one line (ours) with the parser's first complaint in it."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield lambda: [ln.strip() for ln in _read(held).splitlines() if ln.strip()]
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _read(f: Any) -> str:
    f.flush()
    f.seek(0)
    return bytes(f.read()).decode("utf-8", "replace")


def first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else type(exc).__name__


def pinocchio_model(pin: Any, p: Path, text: str) -> Any:
    """Pinocchio's model of the text; whatever it raises (a translated std::exception,
    bad_alloc as MemoryError, …) or says on the process's stderr is one line naming
    the file."""
    with _c_stderr() as said:
        try:
            return pin.buildModelFromXML(text)
        except Exception as exc:  # any std::exception Boost.Python translates
            detail = " ".join((said()[:1] or [first_line(exc)])[0].split())[:300]
    raise FileFormatError(f"{p}: not a URDF that Pinocchio reads ({detail})")
