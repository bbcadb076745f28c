"""The Robot Web Services twin: an IRC5 (RobotWare 6, RWS 1.0) running cellcal's RAPID
module ``CellCal``, served over HTTP with aiohttp on a loopback address, for the
``abb-rws`` driver, ``cellcal mock abb-rws``, ``cellcal run --mock`` and abb-robot-client.
With ``dialect=RWS2`` and an SSL context it is an OmniCore (RobotWare 7, RWS 2.0) instead:
HTTPS, basic authentication, ``Accept`` with ``;v=2.0`` required (406 without), fields
in ``state[0]``, errors in ``status``, the actions and RAPID data at RWS 2.0's paths
(``rw/rapid/symbol/RAPID/T_ROB1/CellCal/<var>/data``, ``rw/rapid/execution/stop``,
``rw/panel/ctrl-state``, ``rw/mastership/edit/request``); the collections (tasks, event
log) keep RWS 1.0's shape.

What it serves, as a controller does (docs/robots.md, "ABB"):

* digest authentication (realm ``validusers@robapi.abb``, qop ``auth``, MD5; the user
  ``Default User``/``robotics`` unless given), then the session cookies
  ``-http-session-`` and ``ABBCX`` (a request with a known session cookie needs no
  digest); a 401 carries the challenge and a JSON body;
* ``rw/system``, ``rw/panel/ctrlstate`` (and ``?action=setctrlstate``), ``rw/panel/opmode``,
  ``rw/panel/speedratio``, ``rw/rapid/execution`` (and ``?action=start|stop|resetpp``),
  ``rw/rapid/tasks``, ``rw/rapid/symbol/data/RAPID/T_ROB1[/CellCal]/<var>`` (and
  ``?action=set``), ``rw/motionsystem/mechunits/ROB_1/jointtarget``, ``rw/mastership``,
  ``rw/elog/0``, ``users/rmmp`` and its poll; replies ``application/json`` exactly
  (abb-robot-client requires it), values as strings, the fields in
  ``_embedded._state[0]``, errors in ``_embedded.status`` with ABB's codes;
* the loop: the same controller model as the KUKA twins (``mocks/kuka/krc.py``: target,
  speed, sequence, acknowledgement, the simulated motion), its RAPID variables
  ``cc_target``, ``cc_seq``, ``cc_ack``, ``cc_speed``; a target beyond the joint limits
  stops RAPID with an event log entry.

Faults (:class:`RwsFaults`, settable at run time): the operating mode (a write in
``MANR``/``MANF`` is refused: 400, -1073414146, no RMMP), motors off, RAPID stopped,
mastership held by another client (a write: 403, -1073445862), a loop that hangs.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import logging
import re
import secrets
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cellcal.drivers.abb_rws_dialects import (
    HELD_ELSEWHERE,
    REALM,
    REFUSED,
    RWS1,
    Dialect,
    RapidValueError,
    format_jointtarget,
    format_num,
    parse_jointtarget,
    parse_num,
)
from cellcal.drivers.kuka_kvp_wire import format_axes
from cellcal.mocks.kuka.krc import KrcController, krc_for_cell
from cellcal.mocks.twins import ABB_HOST, RunningTwin

if TYPE_CHECKING:
    from aiohttp import web

    from cellcal.drivers.abb_rws import AbbRwsOptions
    from cellcal.mocks.simulated_cell import SimulatedCell

log = logging.getLogger("cellcal.mocks.abb")

VARS = ("cc_target", "cc_seq", "cc_ack", "cc_speed")
_SYMBOL = re.compile(r"/rw/rapid/symbol/data/RAPID/T_ROB1(?:/CellCal)?/([A-Za-z_][A-Za-z0-9_]*)")
_RWS2_SYMBOL = re.compile(
    r"/rw/rapid/symbol/RAPID/T_ROB1/(?:CellCal/)?([A-Za-z_][A-Za-z0-9_]*)/data"
)
_RWS2_ACTION = re.compile(r"/rw/rapid/execution/(start|stop|resetpp)")
_RWS2_MASTERSHIP = re.compile(r"/rw/mastership(?:/edit|/motion|/rapid)?/(request|release)")
_DIGEST_FIELD = re.compile(r'(\w+)=(?:"([^"]*)"|([^,\s]*))')
JSON = "application/json"


@dataclass
class RwsFaults:
    opmode: str = "AUTO"  # AUTO, MANR, MANF
    motors_on: bool = True
    running: bool = True
    mastership_held: bool = False
    hang: bool = False  # RAPID runs but never acknowledges (a loop stuck in a WaitUntil)


@dataclass
class _Auth:
    user: str
    password: str
    nonce: str = field(default_factory=lambda: secrets.token_hex(16))
    sessions: set[str] = field(default_factory=set)


def _md5(text: str) -> str:
    return hashlib.md5(text.encode("utf-8"), usedforsecurity=False).hexdigest()


class RwsTwin:
    """An IRC5 running the CellCal module, behind RWS 1.0; see the module docstring."""

    def __init__(
        self,
        controller: KrcController,
        *,
        user: str = "Default User",
        password: str = "robotics",
        faults: RwsFaults | None = None,
        system_name: str = "IRB 140",
        dialect: Dialect = RWS1,
        ssl_context: Any = None,
    ) -> None:
        self.dialect = dialect
        self.ssl_context = ssl_context
        self.controller = controller
        self.system_name = system_name
        self.faults = faults or RwsFaults()
        self.auth = _Auth(user, password)
        self.elog: list[str] = []
        self.requests: list[tuple[str, str]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self.base = ""

    # ------------------------------------------------------------------ serving

    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        from aiohttp import web

        ready = threading.Event()
        bound: list[tuple[str, int]] = []
        failed: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            app = web.Application()
            app.router.add_route("*", "/{tail:.*}", self._handle)
            self._runner = web.AppRunner(app, access_log=None)
            try:
                loop.run_until_complete(self._runner.setup())
                site = web.TCPSite(self._runner, host, port, ssl_context=self.ssl_context)
                loop.run_until_complete(site.start())
                server = site._server
                assert server is not None
                sockname = server.sockets[0].getsockname()  # type: ignore[attr-defined]
                bound.append((str(sockname[0]), int(sockname[1])))
            except BaseException as exc:
                failed.append(exc)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self._runner.cleanup())
            loop.close()

        self._thread = threading.Thread(target=run, name="abb-rws-twin", daemon=True)
        self._thread.start()
        ready.wait(10)
        if failed:
            raise failed[0]
        if not bound:
            raise RuntimeError("the RWS twin did not start")
        scheme = "https" if self.ssl_context is not None else "http"
        self.base = f"{scheme}://{bound[0][0]}:{bound[0][1]}"
        return bound[0]

    def stop(self) -> None:
        if self._loop is not None and self._thread is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)
            self._thread = None

    # ------------------------------------------------------------------ HTTP

    def _reply(self, status: int, doc: Any | None = None, **headers: str) -> web.Response:
        from aiohttp import web

        if doc is None:
            return web.Response(status=status, headers=headers)
        import json

        return web.Response(
            status=status, body=json.dumps(doc).encode(), headers={"Content-Type": JSON, **headers}
        )

    def _error(self, status: int, code: int, msg: str) -> web.Response:
        return self._reply(status, self.dialect.wrap_error(code, msg))

    def _state(self, fields: dict[str, Any]) -> web.Response:
        return self._reply(200, self.dialect.wrap(fields, self.base + "/"))

    def _authorised(self, request: web.Request) -> str | None:
        """The session cookie to set (or "" when the request already had one); None when
        the request is not authorised."""
        a = self.auth
        if request.cookies.get("-http-session-") in a.sessions:
            return ""
        header = request.headers.get("Authorization", "")
        if self.dialect.version == 2:
            expected_basic = base64.b64encode(f"{a.user}:{a.password}".encode()).decode()
            if header != f"Basic {expected_basic}":
                return None
            session = f"{len(a.sessions) + 1}::http.session::{secrets.token_hex(16)}"
            a.sessions.add(session)
            return session
        if not header.startswith("Digest "):
            return None
        f = {m.group(1): m.group(2) if m.group(2) is not None else m.group(3)
             for m in _DIGEST_FIELD.finditer(header[7:])}  # fmt: skip
        if f.get("username") != a.user or f.get("realm") != REALM or f.get("nonce") != a.nonce:
            return None
        ha1 = _md5(f"{a.user}:{REALM}:{a.password}")
        ha2 = _md5(f"{request.method}:{f.get('uri', '')}")
        expected = _md5(f"{ha1}:{a.nonce}:{f.get('nc')}:{f.get('cnonce')}:{f.get('qop')}:{ha2}")
        if f.get("response") != expected:
            return None
        session = f"{len(a.sessions) + 1}::http.session::{secrets.token_hex(16)}"
        a.sessions.add(session)
        return session

    async def _handle(self, request: web.Request) -> web.Response:
        session = self._authorised(request)
        if session is None:
            challenge = (
                f'Basic realm="{REALM}"'
                if self.dialect.version == 2
                else f'Digest realm="{REALM}", domain="/", qop="auth", '
                f'nonce="{self.auth.nonce}", opaque="799d5", algorithm="MD5", stale="FALSE"'
            )
            return self._reply(
                401,
                RWS1.wrap_error(-1, "authentication required"),
                **{"WWW-Authenticate": challenge},
            )
        if self.dialect.version == 2 and ";v=2.0" not in request.headers.get("Accept", ""):
            return self._error(406, -1073445879, "Accept must name version 2.0 (;v=2.0)")
        form = dict(await request.post()) if request.method == "POST" else {}
        self.requests.append((request.method, request.path_qs))
        path, action = request.path.rstrip("/"), request.query.get("action")
        if self.dialect.version == 2:
            path, action = _as_rws1(request.method, path)
        with self.controller.lock:
            response = self._route(request.method, path, action, form)
        if session:
            response.set_cookie("-http-session-", session, path="/")
            response.set_cookie("ABBCX", str(len(self.auth.sessions)), path="/")
        return response

    # ------------------------------------------------------------------ resources

    def _route(
        self, method: str, path: str, action: str | None, form: dict[str, Any]
    ) -> web.Response:
        c, f = self.controller, self.faults
        self._sync()
        if path.endswith("/users/rmmp/poll"):
            return self._state({"_type": "user-rmmp-poll", "_title": "poll", "status": "GRANTED"})
        if path == "/users/rmmp" and method == "POST":
            return self._reply(202, RWS1.wrap({}, self.base))
        if path == "/rw/system":
            return self._state(
                {"_type": "sys-system", "_title": "system", "name": self.system_name,
                 "rwversion": "6.15.06.00", "major": "6", "minor": "15"}
            )  # fmt: skip
        if path == "/rw/panel/ctrlstate":
            if method == "POST" and action == "setctrlstate":
                f.motors_on = form.get("ctrl-state") == "motoron"
                return self._reply(204)
            return self._state(
                {"_type": "pnl-ctrlstate", "_title": "ctrlstate",
                 "ctrlstate": "motoron" if f.motors_on else "motoroff"}
            )  # fmt: skip
        if path == "/rw/panel/opmode":
            return self._state({"_type": "pnl-opmode", "_title": "opmode", "opmode": f.opmode})
        if path == "/rw/panel/speedratio":
            if method == "POST":
                return self._reply(204)
            return self._state(
                {"_type": "pnl-speedratio", "_title": "speedratio", "speedratio": "100"}
            )
        if path == "/rw/rapid/execution":
            if method == "POST" and action in ("start", "stop", "resetpp"):
                if action == "stop":
                    c.write("CC_STOP", "TRUE")
                elif action == "start":
                    c.ack = c.seq  # main's first line: start idle
                f.running = action == "start"
                self._sync()
                return self._reply(204)
            return self._state(
                {"_type": "rap-execution", "_title": "execution",
                 "ctrlexecstate": "running" if f.running else "stopped", "cycle": "forever"}
            )  # fmt: skip
        if path == "/rw/rapid/tasks":
            return self._reply(200, {"_links": {}, "_embedded": {"_state": [
                {"_type": "rap-task-li", "_title": "T_ROB1", "name": "T_ROB1", "type": "normal",
                 "taskstate": "started", "excstate": "started" if f.running else "stopped",
                 "active": "On", "motiontask": "TRUE"}]}})  # fmt: skip
        if path == "/rw/motionsystem/mechunits/ROB_1/jointtarget":
            q = c.q_now()
            fields = {"_type": "ms-jointtarget", "_title": "ROB_1"}
            fields |= {f"rax_{i + 1}": f"{v:.6f}" for i, v in enumerate(q)}
            fields |= {f"eax_{x}": "9E+09" for x in "abcdef"}
            return self._state(fields)
        if path in ("/rw/mastership", "/rw/mastership/rapid"):
            if f.mastership_held and action == "request":
                return self._error(
                    403, HELD_ELSEWHERE, "Requested resource is held by someone else"
                )
            return self._reply(204)
        if path == "/rw/elog/0":
            return self._reply(200, {"_links": {}, "_embedded": {"_state": [
                {"_type": "elog-message-li", "_title": f"/rw/elog/0/{i + 1}", "msgtype": "3",
                 "code": "50050", "tstamp": "2026-11-28 T  10:00:00", "title": text,
                 "desc": text, "conseqs": "", "causes": "", "actions": "", "argc": "0"}
                for i, text in enumerate(self.elog)]}})  # fmt: skip
        m = _SYMBOL.fullmatch(path)
        if m:
            return self._symbol(method, m.group(1), action, form)
        return self._error(404, -1073445866, f"no resource {path}")

    def _symbol(
        self, method: str, var: str, action: str | None, form: dict[str, Any]
    ) -> web.Response:
        c, f = self.controller, self.faults
        if var not in VARS:
            return self._error(400, REFUSED, f"symbol {var} not found")
        if method == "GET":
            values = {
                "cc_target": format_jointtarget(list(c.target)),
                "cc_seq": format_num(c.seq),
                "cc_ack": format_num(c.ack),
                "cc_speed": format_num(c.speed),
            }
            return self._state({"_type": "rap-data", "_title": f"RAPID/T_ROB1/CellCal/{var}",
                                "value": values[var]})  # fmt: skip
        if action != "set":
            return self._error(400, -1073445879, "invalid argument")
        if f.mastership_held:
            return self._error(403, HELD_ELSEWHERE, "Requested resource is held by someone else")
        if f.opmode != "AUTO":
            return self._error(400, REFUSED, "write refused: manual mode without RMMP")
        text = str(form.get("value", ""))
        try:
            if var == "cc_target":
                c.write("CC_TARGET", format_axes(parse_jointtarget(text, var)))
            else:
                key = {"cc_seq": "CC_SEQ", "cc_ack": "CC_ACK", "cc_speed": "CC_SPEED"}[var]
                if c.write(key, str(round(parse_num(text, var)))) is None:
                    return self._error(400, REFUSED, f"value {text[:30]} refused")
        except RapidValueError as exc:
            return self._error(400, -1073445879, str(exc))
        self._sync()
        return self._reply(204)

    def _sync(self) -> None:
        """The controller model follows the panel: motors, RAPID running; a target into
        a limit, or the simulated cell's protective stop, stops RAPID with an event log
        entry."""
        c, f = self.controller, self.faults
        c.faults.mode = "#AUT" if f.opmode == "AUTO" else "#T1"
        c.faults.drives_on = f.motors_on
        c.faults.no_ack = f.hang or not f.running
        c.step()
        if c.stop_message:
            c.acknowledge_stop_message()
            f.running = False
            inside = all(lo <= v <= hi for v, (lo, hi) in zip(c.target, c.limits, strict=True))
            self.elog.append(
                "50050 Position outside reach: cc_target beyond a joint limit"
                if not inside
                else "20205 Protective stop: RAPID stopped (the simulated cell's fault)"
            )


def _as_rws1(method: str, path: str) -> tuple[str, str | None]:
    """An RWS 2.0 request's resource and action in RWS 1.0's terms (the RWS 1.0 form of
    RAPID data does not exist in 2.0: it stays unknown)."""
    if path.startswith("/rw/rapid/symbol/data/"):
        return "/rw/unknown", None
    m = _RWS2_SYMBOL.fullmatch(path)
    if m:
        return f"/rw/rapid/symbol/data/RAPID/T_ROB1/CellCal/{m.group(1)}", (
            "set" if method == "POST" else None
        )
    if path == "/rw/panel/ctrl-state":
        return "/rw/panel/ctrlstate", "setctrlstate" if method == "POST" else None
    m = _RWS2_ACTION.fullmatch(path)
    if m:
        return "/rw/rapid/execution", m.group(1)
    m = _RWS2_MASTERSHIP.fullmatch(path)
    if m:
        return "/rw/mastership", m.group(1)
    return path, None


def serve(options: AbbRwsOptions, cell: SimulatedCell, time_scale: float) -> RunningTwin:
    """The twin of the configured ABB robot on an ephemeral port of a loopback address."""
    twin = RwsTwin(krc_for_cell(options.home_deg, cell, time_scale), system_name=cell.model.name)
    host, port = twin.start(ABB_HOST, 0)
    twin_options = options.model_copy(
        update={"address": f"http://{host}:{port}", "rws": 1, "poll_s": 0.005,
                "credentials": None, "credentials_env": None}
    )  # fmt: skip
    return RunningTwin(twin_options, twin)
