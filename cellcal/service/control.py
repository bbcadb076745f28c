"""Where the service's two threads meet: the asyncio loop (control API, status page,
sd_notify, signals) asks, the engine thread acts and reports.

In: pause (deferred or immediate), resume, abort, shutdown, new work — each a method
that checks the state and either changes it or raises :class:`ControlError` with the API's
error code and one line. Out: the state, its reason, the campaign's progress, the
devices' states and the engine's heartbeat, read as one snapshot; and every record
of the campaign, turned into an event for the event stream and handed to the loop
with ``call_soon_threadsafe`` (the ``publish`` function given at construction).

States (``specs``: the service): ``idle``, ``running``, ``pausing`` (a deferred pause:
the pose under way is finished and stored), ``paused``, ``aborting``, ``analysing``,
``stopping`` (SIGTERM or SIGINT). A paused campaign — by an operator, by a device fault, or found
running after a crash — holds the queue until an operator resumes or aborts it.

One campaign is shown at a time (``campaign`` and the last poses): the running one, else
the one held, else the last one; a campaign that starts replaces it and its poses.

Size (about 520 lines, over the 500 of the house's rule): the state machine and the
campaign shown on the status page share one lock and one snapshot; the next split takes
the records turned into events (``record``, ``event_data`` and the unit helpers) into a
module of its own.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcal.campaign.plan import PlannedPose
from cellcal.campaign.records import (
    CampaignEnded,
    CampaignEvent,
    CampaignStarted,
    PoseStored,
    Record,
)
from cellcal.errors import UserError

log = logging.getLogger("cellcal.control")

STATES = ("idle", "running", "pausing", "paused", "aborting", "analysing", "stopping")
#: Device states.
ABSENT, CONNECTING, READY, FAULT = "absent", "connecting", "ready", "fault"
#: The last poses kept for the status page.
RECENT_POSES = 30

Publish = Callable[[str, dict[str, Any]], None]


class ControlError(UserError):
    """A request the state does not allow: the API's error ``code`` and one line."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True)
class Job:
    """What the engine thread runs next: a campaign, fresh from the queue or resumed."""

    campaign_id: int
    resume: bool


def _mm(v: Any) -> list[float]:
    return [round(float(x), 4) for x in np.asarray(v).ravel()]


def _deg(q: Any) -> list[float]:
    return [round(float(x), 4) for x in np.degrees(np.asarray(q)).ravel()]


def sigma_mm(std: Any) -> float | None:
    """The σ shown for a sensor at a pose (status page, ``cellcal campaign watch``): the
    3-D norm √(σx² + σy² + σz²) of the per-axis sample standard deviations (mm), the
    spread of one sample about the pose's mean (not the σ of the mean)."""
    norm = float(np.linalg.norm(np.asarray(std, dtype=np.float64)))
    return round(norm, 6) if np.isfinite(norm) else None


class Control:
    """The thread-safe control object; see the module docstring."""

    def __init__(
        self,
        device_names: list[str],
        publish: Publish,
        wake: Callable[[], None] | None = None,
    ) -> None:
        self._lock = threading.Condition()
        # What goes out waits in one outbox, and ``wake`` asks the loop to drain it once
        # for everything added since it last did (None: each item published at once).
        # A status in it is a mark: the loop takes one snapshot for all the changes.
        self._wake = wake
        self._out_lock = threading.Lock()
        self._outbox: deque[tuple[str, dict[str, Any] | None]] = deque()
        self._status_pending = False
        self._done: set[int] = set()  # the poses stored before the campaign (re)started
        self._dwell_wall_s = 0.0
        self._publish = publish
        self.state = "idle"
        self.reason = "starting: connecting the devices"
        self.devices: dict[str, dict[str, str]] = {
            n: {"state": CONNECTING, "message": ""} for n in device_names
        }
        self.stop = threading.Event()  # abandon the pose under way (pause --now, abort, SIGTERM)
        self.hold = threading.Event()  # finish the pose under way, then stop (pause)
        self.intent = ""  # what a stopped acquisition becomes: paused, aborted, interrupted
        self.blocking: int | None = None  # a paused campaign holds the queue
        self.shutting_down = False
        self.closing = threading.Event()  # set on SIGTERM: every wait of the engine ends
        self.heartbeat = time.monotonic()
        self.campaign: dict[str, Any] | None = None  # the campaign shown
        self.recent: deque[dict[str, Any]] = deque(maxlen=RECENT_POSES)  # its last poses
        #: a campaign's last stored poses, from the database (never raises; any thread)
        self.history: Callable[[int], list[dict[str, Any]]] | None = None
        self.last_end: dict[str, Any] | None = None
        self._resume: int | None = None

    # ------------------------------------------------------------ the engine's side

    def beat(self) -> None:
        self.heartbeat = time.monotonic()

    def next_job(
        self,
        queued: Callable[[], int | None],
        interrupt: Callable[[], bool] = lambda: False,
        timeout: float = 1.0,
    ) -> Job | None:
        """Wait (beating) for work: a resume request, else — unless a paused campaign
        holds the queue — the oldest queued campaign. None on shutdown or when
        ``interrupt()`` is true (a reload)."""
        with self._lock:
            while not self.shutting_down and not interrupt():
                self.beat()
                if self._ready():
                    if self._resume is not None:
                        cid, self._resume = self._resume, None
                        return self._begin(Job(cid, resume=True))
                    if self.blocking is None:
                        cid_q = queued()
                        if cid_q is not None:
                            return self._begin(Job(cid_q, resume=False))
                self._lock.wait(timeout)
            return None

    def _ready(self) -> bool:
        return all(d["state"] == READY for d in self.devices.values())

    def _begin(self, job: Job) -> Job:
        self.stop.clear()
        self.hold.clear()
        self.intent = ""
        self.blocking = None
        self.state = "running"
        self.reason = f"campaign {job.campaign_id}: {'resuming' if job.resume else 'starting'}"
        c = self.campaign if self.campaign and self.campaign["id"] == job.campaign_id else {}
        if not c:
            self.recent.clear()  # another campaign is shown: none of the last one's poses
        kept: dict[str, Any] = {k: c[k] for k in ("stored", "planned", "roles") if k in c}
        self.campaign = {"id": job.campaign_id, "status": "running", "stored": 0, "planned": 0}
        self.campaign.update(kept, phase="starting")
        self._changed()
        return job

    def prepare(self, done: set[int], dwell_wall_s: float) -> None:
        """Before a campaign (re)starts: the poses already stored (progress per role) and
        the dwell in wall seconds (the status page's countdown)."""
        with self._lock:
            self._done = set(done)
            self._dwell_wall_s = dwell_wall_s

    def halted(self) -> str:
        """The status a stopped acquisition ends in (asked by the campaign)."""
        with self._lock:
            return self.intent or "interrupted"

    def finished(self, campaign_id: int, status: str, message: str) -> None:
        """The engine is done with a campaign: it ended in ``status``."""
        with self._lock:
            if status == "paused":
                self.blocking = campaign_id
                self.state, self.reason = "paused", f"campaign {campaign_id} paused: {message}"
            else:
                self.state, self.reason = "idle", f"campaign {campaign_id} {status}: {message}"
            if self.shutting_down:
                self.state = "stopping"
            if self.campaign is not None:  # no ETA once it stops (docs/service.md)
                self.campaign.update(phase=status, status=status)
                self.campaign.pop("eta_s", None)
            self._changed()

    def set_device(self, name: str, state: str, message: str = "") -> None:
        with self._lock:
            self.devices[name] = {"state": state, "message": message}
            if self.state == "idle" and not self.shutting_down:
                if self._ready():
                    self.reason = "devices ready, no campaign running"
                elif state != READY:
                    self.reason = f"{name}: {state}" + (f" ({message})" if message else "")
            self._changed()
            self._lock.notify_all()

    def phase(self, name: str, pose: PlannedPose, t: float) -> None:
        """The engine's phase watcher: the heartbeat, and the pose under way."""
        self.beat()
        with self._lock:
            if self.campaign is None:
                return
            c = self.campaign
            c.update(phase=name, phase_started=time.time())
            if c.get("pose_idx") != pose.idx:  # a new pose (its numbers once)
                c.update(pose_idx=pose.idx, role=pose.role, region=pose.region)
                c.update(target_mm=_mm(pose.target_mm), planned_q_deg=_deg(pose.q))
        self._status_later()

    def record(self, record: Record) -> None:
        """A subscriber of the campaign's record stream: progress in, events out."""
        self.beat()
        before = None  # a resumed campaign's poses stored before this process saw them
        known = len(self.recent)  # changed in this thread only, once the engine runs
        if isinstance(record, CampaignStarted) and known < min(record.done, RECENT_POSES):
            before = self.history(record.campaign_id) if self.history else None  # off the lock
        with self._lock:
            c = self.campaign
            if isinstance(record, CampaignStarted) and c is not None:
                if before is not None:
                    self.recent.clear()
                    self.recent.extend(before)
                if self.state == "running":
                    self.reason = f"campaign {record.campaign_id}: acquiring"
                roles: dict[str, dict[str, int]] = {}
                for p in record.plan.poses:
                    r = roles.setdefault(p.role, {"stored": 0, "planned": 0})
                    r["planned"] += 1
                    r["stored"] += p.idx in self._done
                c.update(stored=record.done, planned=record.total, roles=roles)
                c.update(dwell_wall_s=round(self._dwell_wall_s, 3), started=time.time())
                c["stored_at_start"] = record.done
            elif isinstance(record, PoseStored) and c is not None:
                c["stored"] = record.done
                c["reached_q_deg"] = _deg(record.reached_q)
                c["reached_idx"] = record.pose.idx
                role = c.get("roles", {}).get(record.pose.role)
                if role is not None:
                    role["stored"] += 1
                c["eta_s"] = self._eta(c)
                if record.done == record.total and self.state == "running":
                    self.state = "analysing"
                    self.reason = f"campaign {record.campaign_id}: analysing"
        data = event_data(record)
        if isinstance(record, PoseStored):
            self.recent.append(data)
        if isinstance(record, CampaignEnded):
            self.last_end = data
        self._send(KINDS[type(record)], data)
        if isinstance(record, CampaignStarted):  # the campaign shown, with its poses
            self._send("status", self.snapshot(recent=True))
        elif isinstance(record, (PoseStored, CampaignEnded)):
            self._status_later()

    def show(self, campaign: dict[str, Any], poses: list[Any], end: dict[str, Any] | None) -> None:
        """At start-up: the campaign shown (held, else the last), as the database has it."""
        with self._lock:
            self.campaign, self.last_end = campaign, end
            self.recent.clear()
            self.recent.extend(poses)
            self._changed()

    def _send(self, kind: str, data: dict[str, Any] | None) -> None:
        """Out to the watchers, in order; ``data`` None: a snapshot when it goes."""
        if self._wake is None:
            self._publish(kind, data if data is not None else self.snapshot())
            return
        with self._out_lock:
            if data is None:
                if self._status_pending:
                    return  # the snapshot already asked for will show this change too
                self._status_pending = True
            first = not self._outbox
            self._outbox.append((kind, data))
        if first:
            self._wake()

    def _status_later(self) -> None:
        """The progress changed: a fast engine's changes fold into one snapshot."""
        self._send("status", None)

    def drain(self) -> list[tuple[str, dict[str, Any]]]:
        """The loop's side: what went out since it last drained, snapshots taken now."""
        with self._out_lock:
            items = list(self._outbox)
            self._outbox.clear()
            self._status_pending = False
        return [(k, d if d is not None else self.snapshot()) for k, d in items]

    @staticmethod
    def _eta(c: dict[str, Any]) -> float | None:
        done_now = c["stored"] - c.get("stored_at_start", 0)
        if done_now <= 0 or "started" not in c:
            return None
        per_pose = (time.time() - c["started"]) / done_now
        return round(float(per_pose * (c["planned"] - c["stored"])), 1)

    # ------------------------------------------------------------ the loop's side

    def _changed(self) -> None:
        """The state changed (lock held): tell the watchers."""
        self._send("status", self._snapshot())

    def snapshot(self, *, recent: bool = False) -> dict[str, Any]:
        """The state as one dict; ``recent``: with the last poses (for a new watcher;
        the event stream sends each pose once, as it is stored)."""
        with self._lock:
            snap = self._snapshot()
            if recent:
                snap["recent_poses"] = list(self.recent)
            return snap

    def _snapshot(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "reason": self.reason,
            "campaign": self._campaign_copy(),
            "devices": {k: dict(v) for k, v in self.devices.items()},
            "heartbeat_age_s": round(time.monotonic() - self.heartbeat, 3),
            "paused_campaign": self.blocking,
            "last_end": self.last_end,
        }

    def _campaign_copy(self) -> dict[str, Any] | None:
        """The campaign's progress, for another thread: its lists are replaced, never
        changed in place; only the counts per role change in place."""
        if self.campaign is None:
            return None
        c = dict(self.campaign)
        if "roles" in c:
            c["roles"] = {k: dict(v) for k, v in c["roles"].items()}
        return c

    def work_queued(self) -> None:
        """A campaign was added to the queue, or the engine has something to do."""
        with self._lock:
            self._lock.notify_all()

    def current(self) -> int | None:
        with self._lock:
            return self._current()

    def _current(self) -> int | None:
        if self.state in ("running", "pausing", "aborting", "analysing") and self.campaign:
            return int(self.campaign["id"])
        return None

    def pause(self, campaign_id: int | None, immediate: bool) -> str:
        with self._lock:
            cid = self._current()
            if cid is None or (campaign_id is not None and campaign_id != cid):
                raise ControlError("invalid-state", self._not_running("pause", campaign_id))
            if self.state == "analysing":
                raise ControlError("invalid-state", f"campaign {cid} is being analysed")
            if self.state == "aborting":
                raise ControlError("invalid-state", f"campaign {cid} is being aborted")
            self.intent = "paused"
            self.state = "pausing"
            if immediate:
                self.reason = f"campaign {cid}: pausing now (the pose under way is abandoned)"
                self.stop.set()
            else:
                self.reason = f"campaign {cid}: pausing after the pose under way"
                self.hold.set()
            self._changed()
            return self.state

    def resume(self, campaign_id: int | None, status_of: Callable[[int], str]) -> str:
        with self._lock:
            if self._current() is not None:
                raise ControlError("invalid-state", f"campaign {self._current()} is {self.state}")
            cid = campaign_id if campaign_id is not None else self.blocking
            if cid is None:
                raise ControlError("invalid-state", "no campaign is paused; name the one to resume")
            if self.blocking is not None and cid != self.blocking:
                why = f"campaign {self.blocking} is paused: resume or abort it first"
                raise ControlError("invalid-state", why)
            status = status_of(cid)
            if status not in ("paused", "interrupted", "refused"):
                raise ControlError("invalid-state", f"campaign {cid} is {status}, not resumable")
            if not self._ready():
                raise ControlError("devices-not-ready", self._not_ready())
            self._resume = cid
            self.reason = f"campaign {cid}: resume requested"
            self._changed()
            self._lock.notify_all()
            return "running"

    def abort(self, campaign_id: int | None, status_of: Callable[[int], str]) -> tuple[str, int]:
        """Abort the running campaign (at once, robot stopped), or a paused or queued one
        (returned for the caller to mark ``aborted``)."""
        with self._lock:
            cid = self._current()
            if cid is not None and campaign_id in (None, cid):
                if self.state == "analysing":
                    raise ControlError("invalid-state", f"campaign {cid} is being analysed")
                self.intent = "aborted"
                self.state = "aborting"
                self.reason = f"campaign {cid}: aborting"
                self.stop.set()
                self._changed()
                log.info("campaign %d: abort requested; the robot is stopped at once", cid)
                return self.state, cid
            target = campaign_id if campaign_id is not None else self.blocking
            if target is None:
                raise ControlError("invalid-state", "no campaign is running or paused")
            status = status_of(target)
            if status not in ("paused", "interrupted", "queued", "refused"):
                raise ControlError("invalid-state", f"campaign {target} is {status}")
            if self.blocking == target:
                self.blocking = None
                self.state, self.reason = "idle", f"campaign {target} aborted"
                self._lock.notify_all()
            if self.campaign is not None and self.campaign["id"] == target:
                self.campaign.update(status="aborted", phase="aborted")
                self.campaign.pop("eta_s", None)
            self._changed()
            log.info("campaign %d aborted (it was %s)", target, status)
            return "aborted", target

    def recovered(self, campaign_id: int) -> None:
        """A campaign found running or paused at start-up: it holds the queue."""
        with self._lock:
            self.blocking = campaign_id
            self.state = "paused"
            self.reason = (
                f"campaign {campaign_id} was interrupted by a restart; "
                f"cellcal campaign resume {campaign_id} (or abort {campaign_id})"
            )
            self._changed()

    def shutdown(self, why: str = "SIGTERM") -> None:
        """SIGTERM or SIGINT (``why``, the signal's name): stop at the next safe point."""
        with self._lock:
            self.shutting_down = True
            self.closing.set()
            self.intent = "interrupted"
            self.state = "stopping"
            self.reason = f"stopping ({why})"
            self.stop.set()
            self._changed()
            self._lock.notify_all()

    def _not_running(self, what: str, campaign_id: int | None) -> str:
        if campaign_id is not None:
            return f"cannot {what} campaign {campaign_id}: it is not running"
        return f"no campaign is running (state {self.state})"

    def _not_ready(self) -> str:
        bad = [f"{k} {v['state']}" for k, v in self.devices.items() if v["state"] != READY]
        return "devices not ready: " + ", ".join(bad)


def event_data(record: Record) -> dict[str, Any]:
    """A record as the event stream's JSON."""
    if isinstance(record, CampaignStarted):
        verb = "resumed" if record.resumed else "started"
        return {
            "campaign_id": record.campaign_id,
            "kind": verb,
            "message": f"{verb} with {record.done} of {record.total} poses stored",
            "pose_idx": None,
        }
    if isinstance(record, PoseStored):
        p = record.pose
        return {
            "campaign_id": record.campaign_id,
            "idx": p.idx,
            "role": p.role,
            "region": p.region,
            "stored": record.done,
            "planned": record.total,
            "target_mm": _mm(p.target_mm),
            "planned_q_deg": _deg(p.q),
            "reached_q_deg": _deg(record.reached_q),
            "seconds": round(record.t_end - record.t_start, 3),
            "retries": record.retries,
            "sensors": {
                s.sensor: {"n": s.n, "mean_mm": _mm(s.mean), "std_mm": _mm(s.std)}
                | {"sigma_mm": sigma_mm(s.std)}
                for s in record.statistics
            },
        }
    if isinstance(record, CampaignEvent):
        return {
            "campaign_id": record.campaign_id,
            "kind": record.kind,
            "message": record.message,
            "pose_idx": record.pose_idx,
        }
    s = record.summary
    out: dict[str, Any] = {
        "campaign_id": record.campaign_id,
        "status": record.status,
        "stored": record.stored,
        "planned": record.total,
        "message": record.message,
    }
    if s is not None:
        out["validation_mm"] = {
            "before": {"rms": s.validation_before.rms, "max": s.validation_before.max},
            "after": {"rms": s.validation_after.rms, "max": s.validation_after.max},
            "improvement_pct": s.improvement_pct,
        }
    return out


KINDS: dict[type, str] = {
    CampaignStarted: "event",
    PoseStored: "pose",
    CampaignEvent: "event",
    CampaignEnded: "campaign-end",
}
