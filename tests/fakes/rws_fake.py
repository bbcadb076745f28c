"""A plain fake ABB IRC5 controller (RobotWare 6, Robot Web Services 1.0), for tests only.

Written from public RWS 1.0 facts (and RFC 2617) alone, never from cellcal's own ABB driver
or twin: a second, independent server to prove the driver against. Standard library only:
``ThreadingHTTPServer``, a thread per connection, HTTP/1.1 keep-alive. The RAPID main loop
of module CellCal (``WaitUntil cc_seq <> cc_ack; MoveAbsJ cc_target; cc_ack := seq``) is
evaluated exactly from timestamps whenever the state is looked at, so needs no thread.

Choices where the facts leave room:

- Auth first, then ``json=1`` is required (else 400; no XHTML). A digest needs ``qop=auth``,
  our realm and user, a nonce this fake issued (never expiring) and ``uri=`` equal to the
  request target (RFC 2617 3.2.2.5). A known ``-http-session-`` cookie skips the digest.
- Data URLs may name the module (``RAPID/T_ROB1/CellCal/cc_seq``) or only the task, as for
  global PERS; names match case-insensitively, as in RAPID. A set needs a form-urlencoded
  body with one ``value`` (else 400 -1073445879); checked in the order symbol, opmode,
  mastership, value; allowed whether RAPID runs or not.
- Every ``num`` (the jointtarget's too) is kept as a 32-bit float, as in RAPID, and reads
  back as the shortest ``%G`` text giving that float (integers plain, ``9E+09``).
- The measured jointtarget adds fresh uniform noise of at most 0.0004 deg per read (fixed
  seed), written ``%.5f``; ``q_deg()`` is the true position without noise.
- Motion: smoothstep profile, all axes together; ``cc_speed`` above 100 counts as 100; a
  ``cc_speed`` <= 0 or a target outside the joint limits stops RAPID without moving.
- Motors off, leaving AUTO or ``action=stop`` during a move halt the robot where it is and
  stop RAPID (no ack); while idle they only keep RAPID waiting. ``action=start`` while
  running is a no-op 204; from stopped it runs main's first line, ``cc_ack := cc_seq``.
  Setting ``running`` acts as start/stop.
- Nothing else is served (``/rw/rapid/tasks``, ``/logout``...): 404 with code -1073445859.
  A 401 carries code 401 in the same error body.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import os
import random
import re
import socket
import struct
import threading
import time
from collections.abc import Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, unquote, urlsplit

REALM = "validusers@robapi.abb"
LIMITS = ((-165, 165), (-110, 110), (-110, 70), (-160, 160), (-120, 120), (-400, 400))
VARS = ("cc_target", "cc_seq", "cc_ack", "cc_speed")
NO_SYMBOL, BAD_VALUE, HELD, NOT_FOUND = -1073414146, -1073445879, -1073445862, -1073445859
DATA, FORM = "/rw/rapid/symbol/data/", "application/x-www-form-urlencoded"
CHALLENGE = 'Digest realm="{}", domain="/", qop="auth", nonce="{}", opaque="799d5"'
CHALLENGE += ', algorithm="MD5", stale="FALSE"'
Doc = dict[str, object]
_NUM = r"\s*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\s*"
_JT = re.compile(r"\s*\[\s*\[([^\[\]]*)\]\s*,\s*\[([^\[\]]*)\]\s*\]\s*")
_PARAM = re.compile(r'(\w+)\s*=\s*(?:"((?:[^"\\]|\\.)*)"|([^,\s]*))')


def _md5(text: str) -> str:
    return hashlib.md5(text.encode("utf-8")).hexdigest()


def _f32(text: str) -> float | None:
    if not re.fullmatch(_NUM, text):
        return None
    try:
        return float(struct.unpack("<f", struct.pack("<f", float(text)))[0])
    except (OverflowError, struct.error):
        return None


def _fmt(v: float) -> str:  # the shortest %G text giving back the float32; integers plain
    t = next(t for d in range(1, 10) if _f32(t := f"{v + 0.0:.{d}G}") == v)
    return str(int(float(t))) if float(t).is_integer() and abs(v) < 1e7 else t


def _parse_jt(text: str) -> list[float] | None:
    m = _JT.fullmatch(text)
    if not m:
        return None
    parts = [g.split(",") for g in m.groups()]
    vals = [_f32(p) for g in parts for p in g]
    if [len(g) for g in parts] != [6, 6] or any(v is None for v in vals):
        return None
    return [float(v) for v in vals if v is not None]


def _error(code: int, msg: str) -> Doc:
    return {"_links": {}, "_embedded": {"_state": [], "status": {"code": code, "msg": msg}}}


class _Handler(BaseHTTPRequestHandler):
    protocol_version, disable_nagle_algorithm = "HTTP/1.1", True
    server: _Server

    def log_message(self, format: str, *args: object) -> None:
        """No access log on stderr: the tests read ``requests`` instead."""

    def setup(self) -> None:
        super().setup()
        self.server.fake._track(self.connection, add=True)

    def finish(self) -> None:
        with contextlib.suppress(OSError):
            super().finish()
        self.server.fake._track(self.connection, add=False)

    def do_GET(self) -> None:
        self.server.fake._serve(self)


for _m in ("POST", "PUT", "DELETE"):
    setattr(_Handler, f"do_{_m}", _Handler.do_GET)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    fake: RwsFake


class RwsFake:
    max_speed_deg_s = 150.0

    def __init__(
        self,
        q0_deg: Sequence[float] = (0, 0, 0, 0, 30, 0),
        time_scale: float = 0.0,
        user: str = "Default User",
        password: str = "robotics",
    ) -> None:
        self.time_scale = float(time_scale)
        self.user, self.password = user, password
        self.requests: list[tuple[str, str]] = []
        self._q = [float(v) for v in q0_deg]
        self._target = [*self._q, *[9e9] * 6]
        self._num = {"cc_seq": 0.0, "cc_ack": 0.0, "cc_speed": 10.0}
        self._opmode, self._ctrlstate, self._running = "AUTO", "motoron", True
        self.mastership_held = False
        self._move: tuple[list[float], list[float], float, float, float] | None = None
        self._rng = random.Random(11)
        self._lock = threading.RLock()
        self._nonces: set[str] = set()
        self._sessions: set[str] = set()
        self._conns: set[socket.socket] = set()
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None
        self._url = ""

    # ---- lifecycle -------------------------------------------------------------------
    def start(self, host: str, port: int = 0) -> tuple[str, int]:
        self._server = _Server((host, port), _Handler)
        self._server.fake = self
        self._thread = threading.Thread(
            target=self._server.serve_forever, args=(0.05,), daemon=True
        )
        self._thread.start()
        host, port = str(self._server.server_address[0]), int(self._server.server_address[1])
        self._url = f"http://{host}:{port}"
        return host, port

    def stop(self) -> None:
        if self._server is None:
            return
        self._server.shutdown()
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
        self._server.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._server = self._thread = None

    def _track(self, conn: socket.socket, add: bool) -> None:
        with self._lock:
            (self._conns.add if add else self._conns.discard)(conn)

    # ---- settable state ----------------------------------------------------------------
    def _change(self, name: str, value: object) -> None:
        with self._lock:
            self._advance()
            if name == "_running" and value and not self._running:
                self._num["cc_ack"] = self._num["cc_seq"]  # main's first line
            setattr(self, name, value)
            if not self._running or (self._move is not None and not self._may_move()):
                self._halt()
            self._advance()

    def _get(self, name: str) -> object:
        with self._lock:
            self._advance()
            return getattr(self, name)

    opmode = property(lambda s: s._get("_opmode"), lambda s, v: s._change("_opmode", v))
    ctrlstate = property(lambda s: s._get("_ctrlstate"), lambda s, v: s._change("_ctrlstate", v))
    running = property(lambda s: s._get("_running"), lambda s, v: s._change("_running", bool(v)))

    def q_deg(self) -> list[float]:
        with self._lock:
            self._advance()
            return self._pos(time.monotonic())

    # ---- the RAPID program -------------------------------------------------------------
    def _may_move(self) -> bool:
        return self._running and self._opmode == "AUTO" and self._ctrlstate == "motoron"

    def _pos(self, now: float) -> list[float]:
        if self._move is None:
            return list(self._q)
        q0, q1, t0, dur, _ = self._move
        u = min(max((now - t0) / dur, 0.0), 1.0)
        s = u * u * (3 - 2 * u)
        return [a + (b - a) * s for a, b in zip(q0, q1, strict=True)]

    def _halt(self) -> None:
        if self._move is not None:
            self._q, self._move, self._running = self._pos(time.monotonic()), None, False

    def _advance(self) -> None:
        now = time.monotonic()
        while True:
            t = now
            if self._move is not None:
                _, q1, t0, dur, seq = self._move
                if t0 + dur > now:
                    return
                self._q, self._move, self._num["cc_ack"] = list(q1), None, seq
                t = t0 + dur
            if not self._may_move() or self._num["cc_seq"] == self._num["cc_ack"]:
                return
            seq, target, speed = self._num["cc_seq"], self._target[:6], self._num["cc_speed"]
            inside = all(lo <= v <= hi for v, (lo, hi) in zip(target, LIMITS, strict=True))
            if speed <= 0 or not inside:
                self._running = False
                return
            travel = max(abs(b - a) for a, b in zip(self._q, target, strict=True))
            dur = travel / (self.max_speed_deg_s * min(speed, 100.0) / 100) * self.time_scale
            if dur <= 0:
                self._q, self._num["cc_ack"] = target, seq
            else:
                self._move = (list(self._q), target, t, dur, seq)

    # ---- HTTP ----------------------------------------------------------------------------
    def _serve(self, h: _Handler) -> None:
        try:
            body = h.rfile.read(max(0, int(h.headers.get("Content-Length") or 0)))
        except ValueError:
            h.close_connection = True
            return self._reply(h, 400, _error(BAD_VALUE, "Bad Content-Length"))
        with self._lock:
            self.requests.append((h.command, h.path))
            ok, cookies = self._authorise(h)
            nonce = os.urandom(16).hex()
            if not ok:
                self._nonces.add(nonce)
        if not ok:
            auth = [("WWW-Authenticate", CHALLENGE.format(REALM, nonce))]
            return self._reply(h, 401, _error(401, "Unauthorized"), auth)
        url = urlsplit(h.path)
        query = parse_qs(url.query, keep_blank_values=True)
        extra = [("Set-Cookie", c) for c in cookies]
        if query.get("json") != ["1"]:
            return self._reply(h, 400, _error(BAD_VALUE, "Only json=1 is served"), extra)
        ctype = h.headers.get("Content-Type", "").split(";")[0].strip().lower()
        form = parse_qs(body.decode("utf-8", "replace"), True) if ctype == FORM else None
        path = unquote(url.path).rstrip("/")
        with self._lock:
            self._advance()
            status, doc = self._route(h.command, path, query.get("action", [""])[0], form)
        if status == 200 and doc is not None:
            base = f"{self._url}{path.rsplit('/', 1)[0]}/"
            doc = {"_links": {"base": {"href": base}}, "_embedded": {"_state": [doc]}}
        self._reply(h, status, doc, extra)

    def _authorise(self, h: _Handler) -> tuple[bool, list[str]]:
        jar = dict(p.strip().partition("=")[::2] for p in h.headers.get("Cookie", "").split(";"))
        if jar.get("-http-session-") in self._sessions:
            return True, []
        scheme, _, rest = h.headers.get("Authorization", "").partition(" ")
        if scheme.lower() != "digest":
            return False, []
        p = {m.group(1).lower(): m.group(2) or m.group(3) or "" for m in _PARAM.finditer(rest)}
        if (
            p.get("username") != self.user
            or p.get("realm") != REALM
            or p.get("nonce") not in self._nonces
            or p.get("qop") != "auth"
            or p.get("uri") != h.path
            or p.get("algorithm", "MD5").upper() != "MD5"
        ):
            return False, []
        ha1 = _md5(f"{self.user}:{REALM}:{self.password}")
        ha2 = _md5(f"{h.command}:{p['uri']}")
        want = _md5(f"{ha1}:{p['nonce']}:{p.get('nc', '')}:{p.get('cnonce', '')}:auth:{ha2}")
        if not hmac.compare_digest(want, p.get("response", "").lower()):
            return False, []
        n = len(self._sessions) + 1
        token = f"{n}::http.session::{os.urandom(16).hex()}"
        self._sessions.add(token)
        return True, [f"-http-session-={token}; Path=/", f"ABBCX={n}; Path=/"]

    def _route(
        self, method: str, path: str, action: str, form: dict[str, list[str]] | None
    ) -> tuple[int, Doc | None]:
        if path.startswith(DATA):
            return self._data(method, path[len(DATA) :].split("/"), action, form)
        if method == "POST" and path == "/rw/rapid/execution" and action in ("start", "stop"):
            self._change("_running", action == "start")
            return 204, None
        if method != "GET":
            return 404, _error(NOT_FOUND, "Resource not found")
        q = [v + self._rng.uniform(-0.0004, 0.0004) for v in self._pos(time.monotonic())]
        jt = {f"rax_{i + 1}": f"{v:.5f}" for i, v in enumerate(q)}
        jt |= {f"eax_{c}": "9E+09" for c in "abcdef"}
        exe = {"ctrlexecstate": "running" if self._running else "stopped", "cycle": "forever"}
        state = {
            "/rw/system": ("sys-system", "system", {"name": "IRB 1200", "rwversion": "6.14.00.00"}),
            "/rw/panel/ctrlstate": ("pnl-ctrlstate", "ctrlstate", {"ctrlstate": self._ctrlstate}),
            "/rw/panel/opmode": ("pnl-opmode", "opmode", {"opmode": self._opmode}),
            "/rw/rapid/execution": ("rap-execution", "execution", exe),
            "/rw/motionsystem/mechunits/ROB_1/jointtarget": ("ms-jointtarget", "ROB_1", jt),
        }.get(path)
        if state is None:
            return 404, _error(NOT_FOUND, "Resource not found")
        return 200, {"_type": state[0], "_title": state[1], **state[2]}

    def _data(
        self, method: str, parts: list[str], action: str, form: dict[str, list[str]] | None
    ) -> tuple[int, Doc | None]:
        names = [p.lower() for p in parts]
        var = names[-1]
        if not (
            names[:2] == ["rapid", "t_rob1"]
            and (len(names) == 3 or (len(names) == 4 and names[2] == "cellcal"))
            and var in VARS
        ):
            return 400, _error(NO_SYMBOL, "Symbol not found")
        if method == "GET" and not action:
            rob, ext = (",".join(map(_fmt, x)) for x in (self._target[:6], self._target[6:]))
            text = f"[[{rob}],[{ext}]]" if var == "cc_target" else _fmt(self._num[var])
            title = f"RAPID/T_ROB1/CellCal/{var}"
            return 200, {"_type": "rap-data", "_title": title, "value": text}
        if method != "POST" or action != "set":
            return 404, _error(NOT_FOUND, "Resource not found")
        if self._opmode != "AUTO":
            return 400, _error(NO_SYMBOL, "Not allowed in manual mode without RMMP")
        if self.mastership_held:
            return 403, _error(HELD, "Requested resource is held by someone else")
        texts = (form or {}).get("value", [])
        value = (_parse_jt if var == "cc_target" else _f32)(texts[0]) if len(texts) == 1 else None
        if value is None:
            return 400, _error(BAD_VALUE, "Invalid value")
        if isinstance(value, list):
            self._target = value
        else:
            self._num[var] = value
        self._advance()
        return 204, None

    @staticmethod
    def _reply(
        h: _Handler, status: int, doc: Doc | None, headers: Sequence[tuple[str, str]] = ()
    ) -> None:
        h.send_response(status)
        for k, v in headers:
            h.send_header(k, v)
        if doc is None:
            h.end_headers()
            return
        data = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)
