"""An ABB robot (IRC5 with RobotWare 6, OmniCore with RobotWare 7) through Robot Web
Services and the RAPID module cellcal ships.

The module (``cellcal export robot-program --driver abb-rws``, docs/robots.md) waits
until ``cc_seq <> cc_ack``, moves ``MoveAbsJ cc_target … fine`` at ``cc_speed`` %, waits
until the robot is in position and sets ``cc_ack`` to that ``cc_seq``. The move → settle →
read contract is :class:`~cellcal.drivers.stop_and_measure.HandshakeRobot`'s; this module
is its transport over RWS (``abb_rws_dialects``; httpx, digest authentication for RWS
1.0, basic over HTTPS for RWS 2.0):

* the state: ``rw/panel/ctrlstate`` (``motoron`` needed), ``rw/panel/opmode`` (``AUTO``:
  the manual modes are refused), ``rw/rapid/execution`` (``running``), and the module's
  ``cc_seq``/``cc_ack``: a ``cc_seq`` this driver did not set means another client;
* a move: ``cc_target``, ``cc_speed``, then ``cc_seq`` (RAPID mastership taken implicitly
  by the controller for each write; held elsewhere is one line naming it);
* the measured joints: ``rw/motionsystem/mechunits/ROB_1/jointtarget`` (degrees);
* a stop: ``rw/rapid/execution`` stop.

Credentials are never in the configuration: ``credentials`` names a file holding
``user:password`` (readable by its owner only), ``credentials_env`` an environment
variable holding it; with neither, ABB's factory user (``Default User``) is used, with a
warning. Every HTTP failure, refusal and reply that is not RWS is one line naming the
robot.
"""

from __future__ import annotations

import logging
import os
import ssl
import stat
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers.abb_rws_dialects import (
    DIALECTS,
    HELD_ELSEWHERE,
    REALM,
    REFUSED,
    Dialect,
    RapidValueError,
    format_jointtarget,
    parse_num,
)
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription
from cellcal.drivers.stop_and_measure import ControllerState, HandshakeRobot
from cellcal.errors import DeviceError, InputError
from cellcal.extras import needs

log = logging.getLogger("cellcal.drivers.abb")

FACTORY_USER = ("Default User", "robotics")
_NAME = r"^[A-Za-z][A-Za-z0-9_]{0,31}$"


class AbbRwsOptions(RobotOptions):
    """``[robot]`` with ``driver = "abb-rws"``: ``address`` ``http(s)://host[:port]``;
    ``rws`` 1 (RobotWare 6) or 2 (RobotWare 7), by default from the scheme (http: 1,
    https: 2); ``credentials`` or ``credentials_env`` (see the module docstring);
    ``task`` and ``module`` of the RAPID loop; ``tls_ca`` the controller's certificate
    (or its CA) for HTTPS, ``tls_verify = false`` to accept any (a controller's
    self-signed certificate, on the cell's own network only)."""

    driver: Literal["abb-rws"] = "abb-rws"
    rws: Literal[1, 2] | None = None
    credentials: str | None = None
    credentials_env: Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")] | None = None
    task: Annotated[str, Field(pattern=_NAME)] = "T_ROB1"
    module: Annotated[str, Field(pattern=_NAME)] = "CellCal"
    tls_ca: str | None = None
    tls_verify: bool = True
    move_timeout_s: Positive = 60.0
    poll_s: Annotated[float, Field(gt=0, le=1)] = 0.05
    request_timeout_s: Annotated[float, Field(gt=0, le=60)] = 5.0

    @model_validator(mode="after")
    def _one_source(self) -> AbbRwsOptions:
        if self.credentials is not None and self.credentials_env is not None:
            raise ValueError("give credentials (a file) or credentials_env, not both")
        if not self.address.startswith(("http://", "https://")) and self.address:
            raise ValueError(f"address {self.address!r}: http://host[:port] or https://…")
        return self

    def relative_to(self, folder: Path) -> AbbRwsOptions:
        """``credentials`` and ``tls_ca`` relative to the configuration's folder."""

        def at(path: str | None) -> str | None:
            return path if path is None or Path(path).is_absolute() else str(folder / path)

        return self.model_copy(
            update={"credentials": at(self.credentials), "tls_ca": at(self.tls_ca)}
        )

    def named_files(self) -> dict[str, str]:
        files = {"credentials": self.credentials, "tls_ca": self.tls_ca}
        return {key: path for key, path in files.items() if path is not None}

    def version(self) -> int:
        return self.rws or (2 if self.address.startswith("https://") else 1)


def read_credentials(options: AbbRwsOptions) -> tuple[str, str]:
    """(user, password) from the file or variable the options name; one line when it
    cannot be read or is not ``user:password``."""
    if options.credentials is not None:
        path = Path(options.credentials)
        try:
            info = path.stat()
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise InputError(f"robot.credentials {path}: {exc.strerror or exc}") from None
        if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise InputError(
                f"robot.credentials {path}: readable by others "
                f"(mode {stat.S_IMODE(info.st_mode):o}): chmod 600 it"
            )
        where = f"robot.credentials {path}"
    elif options.credentials_env is not None:
        value = os.environ.get(options.credentials_env)
        if value is None:
            raise InputError(f"robot.credentials_env: ${options.credentials_env} is not set")
        text, where = value, f"${options.credentials_env}"
    else:
        log.warning("abb-rws: no credentials configured: ABB's factory user %r", FACTORY_USER[0])
        return FACTORY_USER
    user, sep, password = text.strip("\r\n").partition(":")
    if not sep or not user:
        raise InputError(f"{where}: expected one line user:password")
    return user, password


class AbbRwsRobot(HandshakeRobot):
    """An ABB robot through RWS and the shipped RAPID module; see the module docstring."""

    family = "abb-rws"

    def __init__(self, options: AbbRwsOptions, *, name: str = "abb-robot") -> None:
        super().__init__(
            name, options.address, timeout_s=options.move_timeout_s, poll_s=options.poll_s
        )
        self.options = options
        self.dialect: Dialect = DIALECTS[options.version()]
        self._client: Any = None
        self.system: dict[str, Any] = {}

    @classmethod
    def from_options(cls, options: AbbRwsOptions, context: DeviceContext) -> AbbRwsRobot:
        return cls(options)

    def describe(self) -> DeviceDescription:
        s = self.system
        return DeviceDescription(
            ROBOT_NAME, self.family, self.where, "ABB", s.get("name"), s.get("rwversion")
        )

    # ------------------------------------------------------------------ HTTP

    def _open(self) -> None:
        with needs('the robot driver "abb-rws"'):
            import httpx
        user, password = read_credentials(self.options)
        auth: Any = (
            httpx.DigestAuth(user, password)
            if self.dialect.version == 1
            else httpx.BasicAuth(user, password)
        )
        verify: Any = self.options.tls_verify
        if self.options.tls_ca is not None:
            try:
                verify = ssl.create_default_context(cafile=self.options.tls_ca)
            except (OSError, ssl.SSLError) as exc:
                raise InputError(f"robot.tls_ca {self.options.tls_ca}: {exc}") from None
        self._client = httpx.Client(
            base_url=self.options.address.rstrip("/"),
            auth=auth,
            headers=self.dialect.headers,
            timeout=self.options.request_timeout_s,
            verify=verify,
        )
        try:
            self.system = self._get(self.dialect.system)
        except DeviceError:
            self._close()
            raise
        log.info(
            "%s: ABB %s, RobotWare %s, at %s (RWS %d.0)",
            self.name,
            self.system.get("name"),
            self.system.get("rwversion"),
            self.where,
            self.dialect.version,
        )

    def _close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def _request(
        self, method: str, path: str, form: dict[str, str] | None = None, action: str | None = None
    ) -> Any:
        import httpx

        if self._client is None:
            self._open()
        d = self.dialect
        headers = {"Content-Type": d.form_type} if form is not None else None
        try:
            res = self._client.request(
                method, path, params=d.query(action), data=form, headers=headers
            )
        except httpx.ConnectError as exc:
            self._close()
            if "CERTIFICATE" in str(exc).upper():
                raise self._error(
                    f"the controller's certificate is not trusted ({exc}): give its "
                    "certificate as robot.tls_ca"
                ) from None
            raise self._error(f"cannot connect ({exc}): is Robot Web Services reachable?") from None
        except httpx.TimeoutException:
            self._close()
            raise self._error(
                f"no answer to {method} {path} within {self.options.request_timeout_s:g} s"
            ) from None
        except httpx.HTTPError as exc:
            self._close()
            raise self._error(f"{method} {path} failed: {exc}") from None
        if res.status_code == 401:
            scheme = res.headers.get("www-authenticate", "").partition(" ")[0].lower()
            if scheme in ("basic", "digest") and scheme != ("digest", "basic")[d.version - 1]:
                other = 2 if scheme == "basic" else 1
                raise self._error(
                    f"the controller asks for {scheme} authentication: it speaks RWS {other}.0 "
                    f"(RobotWare {other + 5}), not {d.version}.0: set robot.rws = {other}"
                )
            raise self._error(
                f"the controller refused the credentials (HTTP 401, realm {REALM}): check "
                "robot.credentials or robot.credentials_env"
            )
        doc: Any = None
        if res.content:
            try:
                doc = res.json()
            except ValueError:
                raise self._error(
                    f"{method} {path}: HTTP {res.status_code}, not JSON "
                    f"({res.headers.get('content-type')}): is it Robot Web Services "
                    f"{d.version}.0 (robot.rws)?"
                ) from None
        if res.status_code >= 400:
            raise self._refusal(method, path, res.status_code, doc)
        return doc

    def _refusal(self, method: str, path: str, status: int, doc: Any) -> DeviceError:
        code, msg = self.dialect.error(doc)
        if code == HELD_ELSEWHERE:
            why = (
                "RAPID mastership is held by another client (RobotStudio, the FlexPendant "
                "or another program): release it"
            )
        elif code == REFUSED and method == "POST":
            why = "the controller refused the write (manual mode, or no mastership)"
        elif status == 404:
            o = self.options
            why = f"no such resource: is the {o.module} module loaded in task {o.task}?"
        else:
            why = "refused"
        detail = f"; {code}: {msg}" if code is not None else ""
        return self._error(f"{method} {path}: HTTP {status}: {why}{detail}")

    def _get(self, path: str) -> dict[str, Any]:
        doc = self._request("GET", path)
        try:
            return self.dialect.item(doc)
        except RapidValueError as exc:
            raise self._error(f"GET {path}: {exc}") from None

    def _symbol(self, var: str) -> str:
        return self.dialect.symbol(self.options.task, self.options.module, var)

    def _num(self, var: str) -> int:
        item = self._get(self._symbol(var))
        try:
            value = parse_num(str(item.get("value")), var)
        except RapidValueError as exc:
            raise self._error(str(exc)) from None
        return int(value)

    def set_symbol(self, var: str, value: str) -> None:
        self._request("POST", self._symbol(var), {"value": value}, action="set")

    # ------------------------------------------------------------------ the contract's transport

    def _state(self) -> ControllerState:
        d = self.dialect
        ctrl = str(self._get(d.ctrlstate).get("ctrlstate"))
        mode = str(self._get(d.opmode).get("opmode"))
        execution = str(self._get(d.execution).get("ctrlexecstate"))
        seq, ack = self._num("cc_seq"), self._num("cc_ack")
        text = f"ctrlstate {ctrl}, opmode {mode}, execution {execution}, cc_seq {seq}, cc_ack {ack}"
        reason = None
        if mode != "AUTO":
            reason = (
                f"controller in {mode}: the RAPID loop runs unattended in AUTO only (the "
                "mode switch on the cabinet or FlexPendant)"
            )
        elif ctrl != "motoron":
            reason = f"motors are not on (ctrlstate {ctrl}): switch them on"
        elif execution != "running":
            reason = (
                f"RAPID is not running (execution {execution}): start main of "
                f"{self.options.module} in {self.options.task}"
            )
        fault = None if reason is None else f"move failed: {reason}"
        return ControllerState(reason, fault, False, ack, text, seq, "cc_seq")

    def _send_move(self, target_deg: Array, speed: float, seq: int) -> None:
        self.set_symbol("cc_target", format_jointtarget([float(v) for v in target_deg]))
        self.set_symbol("cc_speed", str(max(1, min(100, round(speed * 100)))))
        self.set_symbol("cc_seq", str(seq))

    def _read_joints_deg(self) -> Array:
        item = self._get(self.dialect.jointtarget)
        try:
            return np.array([parse_num(str(item.get(f"rax_{i}")), f"rax_{i}") for i in range(1, 7)])
        except RapidValueError as exc:
            raise self._error(f"jointtarget: {exc}") from None

    def _send_stop(self) -> None:
        path, query, form = self.dialect.stop
        self._request("POST", path, form, action="stop" if query.get("action") else None)
