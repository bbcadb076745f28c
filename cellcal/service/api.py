"""The control API: HTTP/1.1 and JSON on a Unix socket (aiohttp), server-sent events
for watching (``event_stream.py``: the hub and the stream, bounded for slow watchers).
A mutating call answers ``202`` once accepted; clients learn the outcome from the event
stream. Errors have one shape: ``{"error": {"code", "message"}}`` with one line of
message, whatever refused the request (``api_requests.py`` reads and checks each with
bounds before anything acts on it). Every mutating call records the caller
(SO_PEERCRED) in the campaign's events."""

from __future__ import annotations

import asyncio
import json
import logging
import pwd
import socket
import sqlite3
import struct
import tomllib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aiohttp import web

from cellcal import __version__
from cellcal.campaign.kinds import DEFAULT_KIND, kind_named, shown_kinds
from cellcal.campaign.runner import plan_campaign, queue_campaign
from cellcal.config import CellConfig, config_from_dict, relative_to
from cellcal.config_earlier import upgrade_stored
from cellcal.errors import CellcalError
from cellcal.reports.folder import list_campaigns
from cellcal.service.api_requests import (
    MAX_BODY,
    PAUSE_FIELDS,
    START_FIELDS,
    RequestError,
    StartRequest,
    campaign_number,
    check_deadline,
    limit_of,
    pause_request,
    quote,
    read_body,
    start_request,
)
from cellcal.service.control import Control, ControlError
from cellcal.service.event_stream import WATCHER_BACKLOG as WATCHER_BACKLOG
from cellcal.service.event_stream import EventHub as EventHub  # the service's hub
from cellcal.service.event_stream import event_stream
from cellcal.store.database import Store

log = logging.getLogger("cellcal.service")

API_VERSION = 1
SO_PEERGROUPS = 59  # Linux 4.13+, not in Python's socket module


@dataclass(frozen=True)
class Peer:
    pid: int
    uid: int
    gid: int
    groups: tuple[int, ...]

    @property
    def user(self) -> str:
        try:
            return pwd.getpwuid(self.uid).pw_name
        except KeyError:
            return str(self.uid)

    def __str__(self) -> str:
        return f"uid {self.uid} ({self.user}), pid {self.pid}"


def peer_of(request: web.Request) -> Peer | None:
    """The process at the other end of the Unix socket, from the kernel."""
    transport = request.transport
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is None or sock.family != socket.AF_UNIX:
        return None
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_PEERGROUPS, 4 * 256)
        groups = struct.unpack(f"{len(raw) // 4}I", raw)
    except OSError:
        groups = ()
    return Peer(pid, uid, gid, tuple(groups))


def _error(status: int, code: str, message: str) -> web.Response:
    return web.json_response({"error": {"code": code, "message": message}}, status=status)


STATUS_OF_CODE = {
    "invalid-state": 409,
    "invalid-params": 400,
    "not-found": 404,
    "devices-not-ready": 503,
    "forbidden": 403,
}


@dataclass
class Service:
    """What the handlers need: the control object, the loop thread's database
    connection, the event hub, the service's configuration and where it listens (and the
    kinds of the campaigns shown so far: a campaign's kind never changes)."""

    control: Control
    store: Store
    hub: EventHub
    config: CellConfig
    config_path: str | None
    mock: bool
    time_scale: float
    socket_path: str
    http: str | None
    group_id: int  # the socket's group: its members may control the service
    kinds: dict[int, str] = field(default_factory=dict)


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
#: The application's service, as aiohttp keeps typed application state.
SERVICE = web.AppKey("svc", Service)


def make_app(svc: Service) -> web.Application:
    app = web.Application(middlewares=[_errors, _allowed(svc)], client_max_size=MAX_BODY)
    app[SERVICE] = svc
    svc.hub.status_view = lambda snap: _with_kind(svc, snap)
    app.router.add_get("/v1/info", info)
    app.router.add_get("/v1/status", status)
    app.router.add_get("/v1/events", events)
    app.router.add_get("/v1/campaigns", campaigns)
    app.router.add_get("/v1/campaigns/{id}", one_campaign)
    app.router.add_post("/v1/campaigns", start)
    app.router.add_post("/v1/campaigns/{id}/{action:pause|resume|abort}", act)
    return app


@web.middleware
async def _errors(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Every refusal in the API's shape, whatever refused: a handler, aiohttp (no such
    route, a method not allowed, a body too large) or a bug (500, logged)."""
    try:
        return await handler(request)
    except RequestError as exc:
        return _error(exc.status, exc.code, exc.message)
    except ControlError as exc:
        return _error(STATUS_OF_CODE.get(exc.code, 400), exc.code, exc.message)
    except web.HTTPNotFound:
        where = quote(request.path)
        return _error(404, "not-found", f"no such resource: {request.method} {where}")
    except web.HTTPMethodNotAllowed:
        where = quote(request.path)
        return _error(405, "invalid-params", f"{request.method} is not allowed on {where}")
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        code = "forbidden" if exc.status == 403 else "invalid-params"
        return _error(exc.status, code, f"{request.method} {quote(request.path)}: {exc.reason}")
    except Exception as exc:
        log.exception("%s %s failed", request.method, quote(request.path))
        message = f"the service failed on this request ({type(exc).__name__}); see its log"
        return _error(500, "internal", message)


def _allowed(svc: Service) -> Any:
    """Beyond the socket's file permissions: the caller must be root, the service's own
    user or a member of the socket's group."""
    import os

    @web.middleware
    async def check(request: web.Request, handler: Handler) -> web.StreamResponse:
        peer = peer_of(request)
        trusted = peer is None or peer.uid in (0, os.getuid())
        if peer is not None and not trusted and svc.group_id not in (peer.gid, *peer.groups):
            return _error(403, "forbidden", f"{peer} is not in the service's group")
        if request.method == "POST":
            check_deadline(request)  # a change its client gave up on is not made
        return await handler(request)

    return check


def _svc(request: web.Request) -> Service:
    svc = request.app[SERVICE]
    return svc


async def info(request: web.Request) -> web.Response:
    import os

    svc = _svc(request)
    return web.json_response(
        {
            "name": "cellcal",
            "version": __version__,
            "api_version": API_VERSION,
            "pid": os.getpid(),
            "db": svc.store.path,
            "socket": svc.socket_path,
            "http": svc.http,
            "config": svc.config_path,
            "mock": svc.mock,
        }
    )


def _queue(store: Store) -> list[int]:
    return store.queued_campaigns()


def _snapshot(svc: Service) -> dict[str, Any]:
    """The control object's snapshot with the queue from the database."""
    snap = _with_kind(svc, svc.control.snapshot(recent=True))
    snap["queue"] = _queue(svc.store)
    if svc.config.fleet is not None:
        snap["fleet"] = _fleet(svc)
    return snap


def _fleet(svc: Service) -> dict[str, Any]:
    """The replication's lag as the outbox says it (``cellcal fleet status``'s figures)."""
    p = svc.store.fleet_progress()
    error = p.state.get("last_error") or None
    return {
        "server": p.state.get("server"),
        "waiting": p.waiting,
        "oldest_waiting": p.oldest_waiting,
        "last_sent": p.state.get("last_sent"),
        "last_error": error,
    }


def _with_kind(svc: Service, snap: dict[str, Any]) -> dict[str, Any]:
    """A status whose campaign shown carries its kind (``calibration``, ``iso9283``), read
    from the database once per campaign (loop thread: the loop's connection)."""
    c = snap.get("campaign")
    if not c or "kind" in c:
        return snap
    cid = int(c["id"])
    if cid not in svc.kinds:
        try:
            svc.kinds[cid] = shown_kinds(svc.store, cid).get(cid, DEFAULT_KIND)
        except (CellcalError, sqlite3.Error) as exc:  # the status goes out without it
            log.warning("campaign %d: its kind not read (%s)", cid, exc)
            return snap
    return {**snap, "campaign": {**c, "kind": svc.kinds[cid]}}


async def status(request: web.Request) -> web.Response:
    return web.json_response(_snapshot(_svc(request)))


async def events(request: web.Request) -> web.StreamResponse:
    """Server-sent events (``event_stream.py``); a new watcher starts with the status."""
    svc = _svc(request)
    return await event_stream(request, svc.hub, lambda: _snapshot(svc))


async def campaigns(request: web.Request) -> web.Response:
    svc = _svc(request)
    limit = limit_of(request.query.get("limit", "50"))
    rows = list_campaigns(svc.store)[-limit:] if limit > 0 else []
    return web.json_response({"campaigns": [r.as_dict() for r in rows]})


def _campaign_id(request: web.Request, svc: Service) -> int | None:
    raw = request.match_info["id"]
    if raw == "current":
        return svc.control.current() or svc.control.blocking
    cid = campaign_number(raw)
    if not svc.store.has_campaign(cid):
        raise ControlError("not-found", f"no campaign {cid} in {svc.store.path}")
    return cid


async def one_campaign(request: web.Request) -> web.Response:
    svc = _svc(request)
    cid = _campaign_id(request, svc)
    if cid is None:
        raise ControlError("not-found", "no campaign is running or paused")
    rows = [r.as_dict() for r in list_campaigns(svc.store) if r.id == cid]
    row = rows[0]
    row["events"] = svc.store.events(cid)
    return web.json_response(row)


def _note(svc: Service, request: web.Request, cid: int, what: str) -> None:
    """The caller of a change, in the campaign's events."""
    peer = peer_of(request)
    who = str(peer) if peer is not None else "unknown caller"
    svc.store.add_event(cid, "operator", f"{what} by {who}", None)


async def act(request: web.Request) -> web.Response:
    svc = _svc(request)
    action = request.match_info["action"]
    body = await read_body(request, PAUSE_FIELDS if action == "pause" else ())
    cid = _campaign_id(request, svc)
    status_of = _status_of(svc.store)
    if action == "pause":
        mode = pause_request(body).mode
        state = svc.control.pause(cid, immediate=mode == "immediate")
        cid = svc.control.current()
        what = f"pause ({mode})"
    elif action == "resume":
        state = svc.control.resume(cid, status_of)
        cid = cid if cid is not None else svc.control.blocking
        what = "resume"
    else:
        state, cid = svc.control.abort(cid, status_of)
        if state == "aborted":  # not running: marked here
            svc.store.set_status(cid, "aborted")
        what = "abort"
    if cid is not None:
        _note(svc, request, cid, what)
    return web.json_response({"state": state, "campaign_id": cid}, status=202)


def _status_of(store: Store) -> Callable[[int], str]:
    def status_of(cid: int) -> str:
        return store.campaign(cid).status

    return status_of


async def start(request: web.Request) -> web.Response:
    svc = _svc(request)
    req = start_request(await read_body(request, START_FIELDS))
    config = _campaign_config(svc, req)
    if req.when == "now" and (
        svc.control.current() is not None or svc.control.blocking is not None
    ):
        busy = svc.control.current() or svc.control.blocking
        raise ControlError(
            "invalid-state",
            f"campaign {busy} is {svc.control.snapshot()['state']}; "
            "start with --queue to run this one after it",
        )
    try:
        # Planning takes a moment (inverse kinematics): off the loop, which keeps serving.
        given = kind_named(req.kind).from_database(req.options or {}, svc.store)  # a check's model
        plan, options = await asyncio.to_thread(plan_campaign, config, req.kind, given)
        check_deadline(request)  # still wanted? (a client that gave up meanwhile: not)
        cid = queue_campaign(
            svc.store,
            config,
            plan,
            config_path=req.config_name,
            mock=svc.mock,
            time_scale=svc.time_scale,
            kind=req.kind,
            options=options,
        )
    except CellcalError as exc:
        raise ControlError("invalid-params", str(exc)) from None
    what = "" if req.kind == DEFAULT_KIND else f"{kind_named(req.kind).title}, "  # planned
    _note(svc, request, cid, f"queued ({what}{len(plan.poses)} poses)")
    svc.control.work_queued()
    return web.json_response({"campaign_id": cid, "n_poses": len(plan.poses)}, status=202)


def _campaign_config(svc: Service, req: StartRequest) -> CellConfig:
    """The campaign's configuration: the service's own, or the text sent, which must
    name the devices the service holds; checked as the engine will read it back."""
    if req.mock is not None and req.mock != svc.mock:
        held = "the simulated cell (--mock)" if svc.mock else "real devices"
        raise ControlError("invalid-params", f"the service runs {held}; mock = {req.mock} asked")
    config = svc.config
    name = req.config_name or "config"
    if req.config_toml:
        try:
            data = tomllib.loads(req.config_toml)
            config = config_from_dict(data, name)
        except tomllib.TOMLDecodeError as exc:
            raise ControlError("invalid-params", f"{name}: not TOML ({exc})") from None
        except CellcalError as exc:
            raise ControlError("invalid-params", str(exc)) from None
        if req.config_name:
            config = relative_to(config, Path(name).parent, database=False)
        for section in ("robot", "sensor"):
            if getattr(config, section) != getattr(svc.config, section):
                raise ControlError(
                    "invalid-params",
                    f"{name}: [{section}] differs from the service's configuration "
                    "(the service holds its devices; restart it with this configuration)",
                )
        # The simulated cell is the service's; the campaign brings its plan and dwell.
        config = config.model_copy(update={"simulation": svc.config.simulation})
    if req.seed is not None:
        if not svc.mock:
            raise ControlError("invalid-params", "seed is for mock mode")
        config = config.model_copy(
            update={"campaign": config.campaign.model_copy(update={"seed": req.seed})}
        )
    # What is queued is read back by the engine (``stored_campaign``): one that would not
    # read back is refused here, not left in the queue for the engine to trip on.
    try:
        stored = upgrade_stored(json.loads(config.model_dump_json()))
        config_from_dict(stored, name, warn=None)
    except CellcalError as exc:
        raise ControlError("invalid-params", str(exc)) from None
    return config
