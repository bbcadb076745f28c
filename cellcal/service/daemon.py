"""``cellcal daemon``: the cell service. One process, never daemonizing itself: the main
thread runs the asyncio loop (control API on a Unix socket, sd_notify, signals), the
engine thread (``worker.py``) runs campaigns on the devices the service holds. The
service holds the database's run lock for its life, so a ``cellcal run`` on the same
file is refused with a line that names the service and its pid.

Start-up: check the socket's folder (the service's own, writable by it alone, else
refused in one line), raise the open files limit and share it out between the
connections and the engine (``connections.py``), lock the database, open it, mark a
campaign found ``running`` or ``paused`` ``interrupted`` (the previous service died
under it) and hold the queue until an operator resumes or aborts it, show that campaign
(else the last one) as the database has it, listen, ``READY=1``; the devices connect in
the engine thread meanwhile (their states in ``STATUS=``). SIGTERM, or SIGINT (Ctrl-C in the
foreground; the twins' processes ignore it and are stopped by the service), each logged
by its name: ``STOPPING=1``, the pose under way is abandoned, the robot stopped, the
campaign ``interrupted``, exit 0. SIGHUP: the
configuration is read again when no campaign runs (else when it ends).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import pwd
import signal
import sqlite3
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiohttp import web

from cellcal.campaign.locks import RunLock, claimed_address, robot_claim
from cellcal.clock import Clock, SimulatedClock, WallClock
from cellcal.config import CellConfig, default_database, load_config
from cellcal.config_files import check_named_files
from cellcal.errors import CampaignError, CellcalError
from cellcal.files.models import load_model
from cellcal.service.api import SERVICE, EventHub, Service, make_app
from cellcal.service.connections import (
    IDLE_TIMEOUT_S,
    AcceptErrors,
    Budget,
    GatedSite,
    descriptor_budget,
    refusal,
)
from cellcal.service.control import Control
from cellcal.service.page import HttpAddress, make_page_app
from cellcal.service.sdnotify import Notifier
from cellcal.service.shown import campaign_view, stored_poses
from cellcal.service.worker import Worker, device_names
from cellcal.store.database import Store

log = logging.getLogger("cellcal.service")

#: Seconds the engine gets to reach a safe point after SIGTERM (TimeoutStopSec is 90).
STOP_GRACE_S = 30.0
#: Unix socket paths are limited to 108 bytes.
MAX_SOCKET_PATH = 107
#: Events that follow one another within this much go out together (s). Woken by every
#: event, the loop cost a fast mock campaign's engine 5-8 % of a 6 ms pose (the GIL and
#: the wake-ups); a real pose lasts seconds, and a watcher sees 10 ms as at once.
BATCH_S = 0.01


@dataclass(frozen=True)
class DaemonOptions:
    config: CellConfig
    config_path: str | None
    mock: bool
    time_scale: float
    db_path: str
    socket_path: str
    http: HttpAddress | None = None


def recover(store: Store, control: Control, previous: str) -> list[int]:
    """Campaigns the previous service left ``running`` or ``paused`` become
    ``interrupted``; the latest of them — or one a SIGTERM interrupted — holds the queue."""
    who = previous or "a previous cellcal process"
    found = []
    for cid, status in store.unfinished_campaigns():
        store.set_status(cid, "interrupted")
        store.add_event(
            cid,
            "recovered",
            f"found {status} at start-up: {who} stopped while it ran; nothing moves until "
            f"an operator resumes it (cellcal campaign resume {cid})",
        )
        found.append(cid)
    stopped = store.last_stopped_by_service()
    hold = found[-1] if found else stopped
    if hold is not None:
        control.recovered(hold)
    return found


def status_line(control: Control) -> str:
    snap = control.snapshot()
    devices = ", ".join(f"{k} {v['state']}" for k, v in snap["devices"].items())
    c = snap["campaign"]
    progress = ""
    if c and snap["state"] in ("running", "pausing", "aborting", "analysing"):
        progress = f" (campaign {c['id']}: pose {c.get('stored', 0)}/{c.get('planned', 0)})"
    return f"{snap['state']}{progress}: {snap['reason']}; devices: {devices}"


def socket_folder(path: str) -> Path:
    """The control socket's folder, created ``0750`` if it is missing; refused unless it
    is the service's user's (or root's) and writable by its owner alone — a folder
    another user made first (a ``/tmp/cellcal`` made in advance) would hand that user
    the service: the socket takes the folder's group, whose members may control it."""
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        raise CampaignError(f"{path}: a Unix socket path is limited to 107 bytes")
    folder = Path(path).parent
    old = os.umask(0o027)
    try:
        folder.mkdir(mode=0o750, parents=True, exist_ok=True)
    except OSError as exc:
        raise CampaignError(f"{folder}: cannot make the socket's folder ({exc.strerror})") from None
    finally:
        os.umask(old)
    me = os.geteuid()
    info = os.lstat(folder)
    if stat.S_ISLNK(info.st_mode) and info.st_uid in (me, 0):
        info = os.stat(folder)  # a link of ours: the folder it names is checked
    where = "$XDG_RUNTIME_DIR/cellcal, or systemd's RuntimeDirectory (/run/cellcal)"
    if info.st_uid not in (me, 0):
        raise CampaignError(
            f"{folder}: the socket's folder belongs to {_user(info.st_uid)}, not to "
            f"{_user(me)} who runs the service: they could take the service over; give a "
            f"folder of the service's own with --socket, e.g. {where}"
        )
    if not stat.S_ISDIR(info.st_mode):
        raise CampaignError(f"{folder}: not a folder; give the socket's folder with --socket")
    if info.st_mode & 0o022:
        who = "everyone" if info.st_mode & 0o002 else "its group"
        raise CampaignError(
            f"{folder}: the socket's folder is writable by {who} "
            f"(mode {stat.S_IMODE(info.st_mode):04o}): they could take the service over; "
            f"chmod 750 {folder}, or give a folder of the service's own, e.g. {where}"
        )
    return folder


def _user(uid: int) -> str:
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


#: What a client past the control socket's connection limit is answered.
CONTROL_FULL = refusal(
    "503 Service Unavailable",
    "application/json",
    json.dumps(
        {
            "error": {
                "code": "invalid-state",
                "message": "the control socket has all the connections it takes; try again "
                "in a few seconds",
            }
        }
    ).encode(),
)
#: What a browser past the status page's connection limit is answered.
PAGE_FULL = refusal(
    "503 Service Unavailable",
    "text/plain; charset=utf-8",
    b"the status page has all the connections it takes; reload in a few seconds\n",
)


def _runner(app: web.Application) -> web.AppRunner:
    """A site's runner: an idle connection is closed after IDLE_TIMEOUT_S, and a request
    whose client goes away is cancelled (nothing is done for a client that gave up)."""
    return web.AppRunner(
        app, shutdown_timeout=2.0, keepalive_timeout=IDLE_TIMEOUT_S, handler_cancellation=True
    )


async def _listen(runner: web.AppRunner, path: str, limit: int) -> int:
    """Listen on the Unix socket (its folder checked): 0660 in a 0750 folder, created
    under a umask so that no window is open; owned by the folder's group (systemd's
    RuntimeDirectory)."""
    folder = socket_folder(path)
    old = os.umask(0o117)
    try:
        with contextlib.suppress(FileNotFoundError):
            if Path(path).is_socket():
                Path(path).unlink()  # a stale socket of a dead service (the run lock is ours)
        name = f"control socket {path}"
        await GatedSite(runner, path=path, limit=limit, name=name, answer=CONTROL_FULL).start()
    finally:
        os.umask(old)
    gid = folder.stat().st_gid
    with contextlib.suppress(OSError):
        os.chown(path, -1, gid)
    os.chmod(path, 0o660)
    return gid


async def _watchdog(notifier: Notifier, control: Control, interval: float, limit: float) -> None:
    """``WATCHDOG=1`` only while the engine's heartbeat is fresh: a hung engine lets
    systemd's watchdog fire."""
    while True:
        if time.monotonic() - control.heartbeat < limit:
            notifier.watchdog()
        else:
            age = time.monotonic() - control.heartbeat
            log.warning("engine heartbeat %.0f s old: no watchdog ping", age)
        await asyncio.sleep(interval)


async def _status_updates(notifier: Notifier, control: Control, changed: asyncio.Event) -> None:
    last = ""
    while True:
        await changed.wait()
        changed.clear()
        line = status_line(control)
        if line != last:
            notifier.status(line)
            last = line
        await asyncio.sleep(0.5)  # at most two STATUS= per second


class Flusher:
    """Takes what the control's outbox holds to the watchers, on the loop: at once after
    a quiet spell, then at most every ``BATCH_S`` while events keep coming, so that a
    fast campaign does not wake the loop for each event. ``wake`` is the control's (any
    thread: the outbox was empty and is not); ``flush`` runs on the loop."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        drain: Callable[[], list[tuple[str, dict[str, Any]]]],
        publish: Callable[[str, dict[str, Any]], None],
    ) -> None:
        self.loop, self.drain, self.publish = loop, drain, publish
        self.armed = False  # a flush is due within BATCH_S: no need to wake the loop

    def wake(self) -> None:
        if not self.armed:
            self.loop.call_soon_threadsafe(self.flush)

    def flush(self) -> None:
        self.armed = False  # before draining: what comes after the drain wakes anew
        items = self.drain()
        for kind, data in items:
            self.publish(kind, data)
        if items:
            self.armed = True
            self.loop.call_later(BATCH_S, self.flush)


async def serve(opts: DaemonOptions) -> int:
    """Run the service until SIGTERM; the exit code."""
    socket_folder(opts.socket_path)  # refused before anything else is done
    loop = asyncio.get_running_loop()
    loop.set_exception_handler(AcceptErrors())
    budget = descriptor_budget()
    notifier = Notifier()
    hub = EventHub()
    changed = asyncio.Event()

    def publish_here(kind: str, data: dict[str, object]) -> None:
        hub.publish(kind, data)
        if kind == "status":
            changed.set()

    def publish(kind: str, data: dict[str, object]) -> None:
        loop.call_soon_threadsafe(publish_here, kind, data)

    flusher = Flusher(loop, lambda: control.drain(), publish_here)
    control = Control(device_names(opts.config), publish, flusher.wake)
    nominal = load_model(opts.config.robot.model).model
    clock: Clock = SimulatedClock(opts.time_scale) if opts.mock else WallClock()
    holder = f"the cellcal service on {opts.db_path}"
    with (
        RunLock(opts.db_path, "the cellcal service") as lock,
        robot_claim(opts.config, holder, needed=not opts.mock) as claim,
    ):
        store = Store(opts.db_path)
        try:
            recovered = recover(store, control, lock.previous)
            for cid in recovered:
                log.warning("campaign %d was interrupted by a restart; it waits for resume", cid)
            control.history = _history(opts.db_path)
            shown = campaign_view(store, control.blocking)
            if shown is not None:
                control.show(*shown)
            app = make_app(_service(opts, control, store, hub))
            runner = _runner(app)
            await runner.setup()
            svc = runner.app[SERVICE]
            page = await _page(svc, opts.http, budget) if opts.http is not None else None
            svc.group_id = await _listen(runner, opts.socket_path, budget.control)
            worker = Worker(
                control,
                opts.config,
                nominal,
                opts.db_path,
                clock,
                mock=opts.mock,
                robot_address=claimed_address(claim),
            )
            worker.start()
            sender = None
            if opts.config.fleet is not None:  # its own thread and connections
                from cellcal.fleet_sync import Sender

                sender = Sender(opts.db_path, opts.config.fleet, log.info)
                sender.start()
            stopped = asyncio.Event()
            for signum in (signal.SIGTERM, signal.SIGINT):
                args = (signum, control, notifier, stopped)
                loop.add_signal_handler(signum, _on_term, *args)
            loop.add_signal_handler(signal.SIGHUP, _on_hup, opts, svc, worker, notifier)
            tasks = [asyncio.create_task(_status_updates(notifier, control, changed))]
            interval = notifier.watchdog_interval_s
            if interval is not None:
                limit = 2 * interval
                tasks.append(asyncio.create_task(_watchdog(notifier, control, interval, limit)))
            db = Path(opts.db_path)
            default = db == Path(default_database()).resolve()
            log.info(
                "listening on %s (pid %d); database %s%s; reports in %s",
                opts.socket_path,
                os.getpid(),
                db,
                " (the default: neither --db nor storage.database names one)" if default else "",
                db.parent / "reports",
            )
            if svc.http:
                log.info("status page: %s", svc.http)
            notifier.ready(status_line(control))
            ended = asyncio.create_task(stopped.wait())
            dead = asyncio.create_task(asyncio.to_thread(worker.join))
            await asyncio.wait({ended, dead}, return_when=asyncio.FIRST_COMPLETED)
            code = 0
            if not stopped.is_set():  # the engine thread ended by itself: a bug
                log.error("the engine thread stopped: %s", worker.failure)
                control.shutdown("the engine thread stopped")
                code = 1
            await asyncio.wait({dead}, timeout=STOP_GRACE_S)
            if not dead.done():
                log.error("the engine did not stop within %.0f s", STOP_GRACE_S)
                code = 1
            _note_stopped(store, control)
            if sender is not None:
                sender.stop()
            for t in tasks:
                t.cancel()
            hub.close()
            if page is not None:
                await page.cleanup()
            await runner.cleanup()
            with contextlib.suppress(FileNotFoundError):
                Path(opts.socket_path).unlink()
            log.info("stopped")
            return code
        finally:
            store.close()


async def _page(svc: Service, http: HttpAddress, budget: Budget) -> web.AppRunner:
    """The status page's site (GET only); ``svc.http`` becomes its address."""
    runner = _runner(make_page_app(svc, http.host))
    await runner.setup()
    site = GatedSite(
        runner,
        host=http.host,
        port=http.port,
        limit=budget.page,
        name="status page",
        answer=PAGE_FULL,
    )
    try:
        await site.start()
    except OSError as exc:
        await runner.cleanup()
        raise CampaignError(
            f"status page: cannot listen on {http.url()} ({exc.strerror or exc})"
        ) from None
    port = int(runner.addresses[0][1])
    svc.http = http.url(port)
    if not http.loopback:
        log.warning("the status page is served on the network: %s (read-only)", svc.http)
    return runner


def _service(opts: DaemonOptions, control: Control, store: Store, hub: EventHub) -> Service:
    return Service(
        control=control,
        store=store,
        hub=hub,
        config=opts.config,
        config_path=opts.config_path,
        mock=opts.mock,
        time_scale=opts.time_scale,
        socket_path=opts.socket_path,
        http=None,
        group_id=os.getgid(),
    )


def _history(db_path: str) -> Callable[[int], list[dict[str, Any]]]:
    """A campaign's last stored poses, read on a connection of the caller's thread (the
    engine's, when a campaign resumes); none when the read fails (said in the log)."""

    def read(campaign_id: int) -> list[dict[str, Any]]:
        try:
            store = Store(db_path, readonly=True)
            try:
                return stored_poses(store, campaign_id)
            finally:
                store.close()
        except (CellcalError, sqlite3.Error) as exc:
            log.warning("campaign %d: its stored poses not read (%s)", campaign_id, exc)
            return []

    return read


def _note_stopped(store: Store, control: Control) -> None:
    """A campaign SIGTERM interrupted, or the one held, says so: the next service holds
    the queue for it (one only shown, from the database, is left alone)."""
    c = control.campaign
    if c is None or ("started" not in c and c["id"] != control.blocking):
        return
    with contextlib.suppress(CellcalError):
        if store.campaign(int(c["id"])).status == "interrupted":
            store.add_event(
                int(c["id"]),
                "service-stopped",
                f"the service stopped (pid {os.getpid()}); cellcal campaign resume {c['id']}",
            )


def _on_term(signum: int, control: Control, notifier: Notifier, stopped: asyncio.Event) -> None:
    """SIGTERM (systemd) or SIGINT (Ctrl-C in the foreground): the same stop, exit 0."""
    name = signal.Signals(signum).name
    if stopped.is_set():
        log.info("%s: already stopping", name)
        return
    log.info("%s: stopping at the next safe point", name)
    notifier.stopping("stopping: the robot is stopped, the campaign kept resumable")
    control.shutdown(name)
    stopped.set()


def _on_hup(opts: DaemonOptions, svc: Service, worker: Worker, notifier: Notifier) -> None:
    """Read the configuration again; the engine applies it when no campaign runs."""
    if opts.config_path is None:
        log.info("SIGHUP: no configuration file to read again (bundled mock cell)")
        return
    notifier.reloading()
    try:
        config = load_config(opts.config_path)
        check_named_files(config, opts.config_path)
    except CellcalError as exc:
        log.error("SIGHUP: %s; the configuration in use is kept", exc)
    else:
        if not opts.mock and (config.robot.driver, config.robot.address) != (
            svc.config.robot.driver,
            svc.config.robot.address,
        ):
            log.error(
                "SIGHUP: the robot's driver or address changed; the service claims the "
                "robot it started with: systemctl restart cellcal (the configuration in "
                "use is kept)"
            )
            notifier.ready(status_line(svc.control))
            return
        svc.config = config
        worker.reload(config)
        log.info("SIGHUP: %s read again; applied when no campaign runs", opts.config_path)
    notifier.ready(status_line(svc.control))
