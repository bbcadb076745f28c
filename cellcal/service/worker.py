"""The service's engine thread: it holds the devices (connected once, reconnected with
backoff after a fault), takes the next campaign from the control object — a resume
request, else the oldest queued campaign in the database — and runs it on the held
devices through the same campaign code as ``cellcal run``, so every pose is stored
exactly once whatever stops it."""

from __future__ import annotations

import contextlib
import json
import logging
import re
import threading

from cellcal.calib.robot_model import RobotModel
from cellcal.campaign.devices import Devices, build_devices
from cellcal.campaign.payloads import instruction
from cellcal.campaign.records import CampaignEnded, CampaignStarted, Record
from cellcal.campaign.run_parts import Held
from cellcal.campaign.runner import run_stored
from cellcal.clock import Clock, SimulatedClock
from cellcal.config import CellConfig
from cellcal.errors import CellcalError, DeviceError, device_of
from cellcal.files.models import load_model
from cellcal.reports.folder import report_folder, write_report
from cellcal.service.control import CONNECTING, FAULT, READY, Control, Job
from cellcal.store.database import Store, StoreError

log = logging.getLogger("cellcal.service")

#: Seconds between connection attempts after a failure: doubled up to the last.
BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 15.0, 30.0)


def oldest_queued(store: Store) -> int | None:
    return store.oldest_queued()


def device_names(config: CellConfig) -> list[str]:
    return ["robot", *(s.name for s in config.sensor)]


def faulty_device(config: CellConfig, message: str) -> str | None:
    """Which device a connection error names, if any (after the pose it was at, which
    the engine names first: ``pose 3: robot: …``)."""
    message = re.sub(r"^pose \d+: ", "", message)
    for name in device_names(config)[1:]:
        if f"sensor {name}" in message or message.startswith((f"{name}:", f"{name} at ")):
            return name
    head = message.split(":", 1)[0]
    if message.startswith("robot") or "robot." in message:
        return "robot"
    if "robot" in head or config.robot.driver in head:
        return "robot"
    return None


class Worker(threading.Thread):
    def __init__(
        self,
        control: Control,
        config: CellConfig,
        nominal: RobotModel,
        db_path: str,
        clock: Clock,
        *,
        mock: bool,
        robot_address: str | None = None,
    ) -> None:
        super().__init__(name="engine", daemon=True)
        #: where the robot's driver connects: the address the service's claim resolved
        self.robot_address = robot_address
        self.control = control
        self.config = config
        self.nominal = nominal
        self.db_path = db_path
        self.clock = clock
        self.mock = mock
        self.devices: Devices | None = None
        self.connections = 0
        self.failure: BaseException | None = None
        self._reload: CellConfig | None = None

    def reload(self, config: CellConfig) -> None:
        """A configuration read again (SIGHUP): applied before the next campaign, with
        the devices connected afresh if they changed."""
        self._reload = config
        self.control.work_queued()

    def _apply_reload(self) -> None:
        config, self._reload = self._reload, None
        if config is None:
            return
        if (config.robot, config.sensor) != (self.config.robot, self.config.sensor):
            self._disconnect()
        self.config = config
        self.nominal = load_model(config.robot.model).model

    def run(self) -> None:
        try:
            store = Store(self.db_path)  # this thread's own connection
        except BaseException as exc:
            self.failure = exc
            return
        try:
            while not self.control.shutting_down:
                self._apply_reload()
                if self.devices is None and not self._connect():
                    continue
                job = self.control.next_job(
                    lambda: oldest_queued(store), lambda: self._reload is not None
                )
                if job is None:
                    continue
                self._run(store, job)
        except BaseException as exc:  # pragma: no cover - logged, the service exits 1
            log.exception("engine thread failed")
            self.failure = exc
        finally:
            self._disconnect()
            store.close()

    def _connect(self) -> bool:
        """Build the devices (twins in mock mode); on failure wait the backoff."""
        c = self.control
        for name in device_names(self.config):
            c.set_device(name, CONNECTING)
        c.beat()
        try:
            self.devices = build_devices(
                self.config,
                self.nominal,
                self.clock,
                mock=self.mock,
                seed=self.config.simulation.seed,
                noise_stream=self.connections,
                robot_address=self.robot_address,
                report=lambda name, message: c.set_device(name, CONNECTING, message),
            )
        except CellcalError as exc:
            if c.shutting_down:  # stopping: a device that did not connect is no news
                log.info("devices: not connected, the service stops (%s)", exc)
                return False
            message = str(exc)
            self._mark_fault(message, device_of(exc))
            wait = BACKOFF_S[min(self.connections, len(BACKOFF_S) - 1)]
            self.connections += 1
            log.warning("devices: %s; next attempt in %.0f s", message, wait)
            c.closing.wait(wait)
            return False
        self.connections += 1
        for name in device_names(self.config):
            c.set_device(name, READY)
        log.info("devices ready: %s", ", ".join(device_names(self.config)))
        return True

    def _mark_fault(self, message: str, device: str | None = None) -> None:
        """The device the error names (``device``: its ``DeviceError.device``; else the
        one its message names) is at fault; the others wait to reconnect (all at fault
        when none is named)."""
        names = device_names(self.config)
        which = device if device in names else faulty_device(self.config, message)
        for name in device_names(self.config):
            state = FAULT if which in (None, name) else CONNECTING
            self.control.set_device(name, state, message if state == FAULT else "")

    def _dwell_wall_s(self, store: Store, cid: int) -> float:
        """The campaign's dwell in wall seconds (a simulated clock scales it)."""
        campaign = json.loads(store.campaign(cid).config_json).get("campaign", {})
        dwell = float(campaign.get("dwell_s", 0.0))
        if isinstance(self.clock, SimulatedClock):
            return dwell * self.clock.time_scale
        return dwell

    def _disconnect(self) -> None:
        if self.devices is not None:
            with contextlib.suppress(Exception):
                self.devices.close()
            self.devices = None

    def _report(self, store: Store, cid: int) -> str:
        """Write the campaign's report folder beside the database (``reports/campaign-N``);
        a report that cannot be written is said, and costs the campaign nothing."""
        folder = report_folder(store.path, cid)
        try:
            write_report(store, cid, folder)
        except (CellcalError, OSError) as exc:
            log.warning("campaign %d: no report written (%s)", cid, exc)
            return f"; no report written ({exc})"
        return f"; report in {folder}"

    def _run(self, store: Store, job: Job) -> None:
        c = self.control
        cid = job.campaign_id
        assert self.devices is not None
        held = Held(
            hold=c.hold,
            phase=c.phase,
            halted=c.halted,
            on_fault="paused",
            hint=f"campaign {cid} is paused: cellcal campaign resume {cid}",
        )
        log.info("campaign %d: %s", cid, "resuming" if job.resume else "starting")
        message = ""
        failure: Exception | None = None
        started = Started()
        try:
            c.prepare(store.completed_indices(cid), self._dwell_wall_s(store, cid))
            out = run_stored(
                store,
                cid,
                self.devices,
                self.clock,
                stop=c.stop,
                held=held,
                subscribers=[started, c.record],
            )
            message = f"{out.acquisition.stored} of {len(out.plan.poses)} poses stored"
            if out.acquisition.awaiting_payload is not None:  # the operator's turn
                message += (
                    f"; {instruction(out.acquisition.awaiting_payload)}: "
                    f"cellcal campaign resume {cid}"
                )
        except CellcalError as exc:
            message, failure = str(exc), exc
        except Exception as exc:
            message, failure = f"{type(exc).__name__}: {exc}", exc
            log.exception("campaign %d failed", cid)
        status = store.campaign(cid).status
        if failure is not None:
            status = self._after_failure(store, cid, status, failure, message, started.seen)
        if status in ("complete", "refused"):
            message += self._report(store, cid)
        log.info("campaign %d %s: %s", cid, status, message)
        c.finished(cid, status, message)
        if failure is not None and status == "paused" and not c.shutting_down:
            # A device fault: let go of the devices and connect them afresh.
            self._disconnect()
            self._mark_fault(message, device_of(failure))

    def _after_failure(
        self,
        store: Store,
        cid: int,
        status: str,
        failure: Exception,
        message: str,
        started: bool,
    ) -> str:
        """The status a campaign that failed ends in. Never one the engine takes up
        again by itself (``queued``), or the queue would loop on it: an abort asked
        meanwhile ends it ``aborted``; a start that failed for a reason that will not
        change (its stored configuration, its plan: anything but a device or the
        database) ends it ``failed`` with the reason; else (a device fault) it is held
        ``paused`` until an operator resumes it, unless the service stops."""
        c = self.control
        if status not in RUNNABLE:  # complete, aborted, failed, refused: recorded
            return status
        ending = ""
        if c.intent == "aborted":
            ending, why = "aborted", f"aborted while it started ({message})"
        elif not started and lasting(failure):
            ending, why = "failed", f"it cannot start: {message}"
        if ending:
            try:
                store.add_event(cid, "error" if ending == "failed" else "aborted", why)
                store.set_status(cid, ending)
            except CellcalError as exc:  # the database refuses writes: said, held
                log.error("campaign %d: not marked %s (%s)", cid, ending, exc)
            else:
                if ending == "failed":
                    log.error("campaign %d failed: %s", cid, why)
                n = store.campaign(cid).n_poses
                stored = store.pose_count(cid)
                c.record(CampaignEnded(cid, ending, stored, n, why))
                return ending
        if c.shutting_down and not ending:
            return status  # the next service holds it (interrupted) or takes it up, once
        if status in ("running", "interrupted", "queued") or ending:
            # Not recorded by the campaign itself (the store failed?): hold it all the same.
            with contextlib.suppress(CellcalError):
                store.set_status(cid, "paused")
            return "paused"
        return status


#: Statuses the engine runs (or holds): a failure leaves none of them as it was.
RUNNABLE = ("queued", "running", "paused", "interrupted")


class Started:
    """A subscriber of the campaign's records that notes its start record: a failure
    before it is the start's (the configuration, the plan, the devices' description)."""

    def __init__(self) -> None:
        self.seen = False

    def __call__(self, record: Record) -> None:
        if isinstance(record, CampaignStarted):
            self.seen = True


def lasting(failure: BaseException) -> bool:
    """A failure that the same start would meet again: not a device's (it may come
    back), not the database's (a full disk may be freed)."""
    causes = [failure, failure.__cause__, failure.__context__]
    return not any(isinstance(e, (DeviceError, StoreError, OSError)) for e in causes)
