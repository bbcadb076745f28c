"""Robot Web Services as RobotWare 6 (RWS 1.0) and RobotWare 7 (RWS 2.0) speak it: the
resource paths, headers, JSON shapes and RAPID value text the ABB driver and its twin
share — no sockets.

RWS 1.0: HTTP, digest authentication (realm ``validusers@robapi.abb``), ``?json=1`` on
every request, one resource's fields in ``_embedded._state[0]``, an error in
``_embedded.status`` (``code``, ``msg``); actions as ``?action=…``. RWS 2.0: HTTPS,
basic authentication, ``Accept: application/hal+json;v=2.0`` and form bodies typed
``application/x-www-form-urlencoded;v=2.0``, fields in ``state[0]``, an error in
``status``; actions in the path, RAPID data under ``symbol/RAPID/<task>/<module>/<var>/data``
and writes with ``mastership=implicit``.

A RAPID ``jointtarget`` is ``[[j1,…,j6],[e1,…,e6]]`` in degrees, unused external axes
``9E+09``; a ``num`` is a decimal number.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from cellcal.errors import CellcalError

REALM = "validusers@robapi.abb"
UNUSED_AXIS = "9E+09"
#: RWS error codes the driver names (from ABB's documentation and public captures).
HELD_ELSEWHERE = -1073445862  # SYS_CTRL_E_RESOURCE_HELD: mastership held by another
REFUSED = -1073414146  # SYS_CTRL_E_FAIL: e.g. a write without mastership, manual mode
_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_JOINTTARGET = re.compile(r"\[\[([^\[\]]*)\],\[([^\[\]]*)\]\]")


class RapidValueError(CellcalError):
    """RAPID value text that is not the type asked for."""


@dataclass(frozen=True)
class Dialect:
    version: int
    ctrlstate: str
    opmode: str = "/rw/panel/opmode"
    execution: str = "/rw/rapid/execution"
    jointtarget: str = "/rw/motionsystem/mechunits/ROB_1/jointtarget"
    system: str = "/rw/system"

    def symbol(self, task: str, module: str, var: str) -> str:
        if self.version == 1:
            return f"/rw/rapid/symbol/data/RAPID/{task}/{module}/{var}"
        return f"/rw/rapid/symbol/RAPID/{task}/{module}/{var}/data"

    def query(self, action: str | None = None) -> dict[str, str]:
        """The query of a request (an action of RWS 1.0's form)."""
        if self.version == 1:
            return {"json": "1", **({"action": action} if action else {})}
        return {"mastership": "implicit"} if action == "set" else {}

    @property
    def stop(self) -> tuple[str, dict[str, str], dict[str, str]]:
        """Path, query and form of the execution stop."""
        if self.version == 1:
            return self.execution, self.query("stop"), {"stopmode": "stop"}
        return f"{self.execution}/stop", {}, {"stopmode": "stop", "usetsp": "normal"}

    @property
    def headers(self) -> dict[str, str]:
        if self.version == 1:
            return {}
        return {"Accept": "application/hal+json;v=2.0"}

    @property
    def form_type(self) -> str:
        base = "application/x-www-form-urlencoded"
        return base if self.version == 1 else f"{base};v=2.0"

    def item(self, doc: Any) -> dict[str, Any]:
        """The fields of one resource in a reply."""
        try:
            items = doc["_embedded"]["_state"] if self.version == 1 else doc["state"]
            first = items[0]
        except (KeyError, IndexError, TypeError):
            raise RapidValueError("a reply without the resource's state") from None
        if not isinstance(first, dict):
            raise RapidValueError("a reply whose state is not an object")
        return first

    def error(self, doc: Any) -> tuple[int | None, str]:
        """(code, msg) of an error reply, as far as it has them."""
        try:
            status = doc["_embedded"]["status"] if self.version == 1 else doc["status"]
            return int(status["code"]), str(status.get("msg", ""))
        except (KeyError, TypeError, ValueError):
            return None, ""

    def wrap(self, fields: dict[str, Any], base: str) -> dict[str, Any]:
        """A reply holding one resource (for the twin)."""
        links = {"base": {"href": base}}
        if self.version == 1:
            return {"_links": links, "_embedded": {"_state": [fields]}}
        return {"_links": links, "state": [fields]}

    def wrap_error(self, code: int, msg: str) -> dict[str, Any]:
        status = {"code": code, "msg": msg}
        if self.version == 1:
            return {"_links": {}, "_embedded": {"_state": [], "status": status}}
        return {"status": status}


RWS1 = Dialect(1, ctrlstate="/rw/panel/ctrlstate")
RWS2 = Dialect(2, ctrlstate="/rw/panel/ctrl-state")
DIALECTS = {1: RWS1, 2: RWS2}


def parse_num(text: str, what: str) -> float:
    s = str(text).strip()
    if not _NUM.fullmatch(s) or not math.isfinite(float(s)):
        raise RapidValueError(f"{what}: {s[:40]!r} is not a RAPID num")
    return float(s)


def parse_jointtarget(text: str, what: str) -> list[float]:
    """The robot axes (degrees) of a RAPID jointtarget; external axes are ignored."""
    m = _JOINTTARGET.fullmatch(str(text).replace(" ", ""))
    if m is None:
        raise RapidValueError(f"{what}: {text[:60]!r} is not a RAPID jointtarget [[...],[...]]")
    robax = m.group(1).split(",")
    extax = m.group(2).split(",")
    if len(robax) != 6 or len(extax) != 6:
        raise RapidValueError(
            f"{what}: {len(robax)} robot and {len(extax)} external axes, not 6 and 6"
        )
    for v in extax:
        parse_num(v, what)
    return [parse_num(v, what) for v in robax]


def format_jointtarget(deg: list[float]) -> str:
    robax = ",".join(f"{v:.6f}" for v in deg)
    return f"[[{robax}],[{','.join([UNUSED_AXIS] * 6)}]]"


def format_num(value: float) -> str:
    return f"{value:g}" if value != int(value) else str(int(value))
