"""The pieces every campaign run shares, whatever its kind (``runner.py``): the seed,
the devices' descriptions, the configuration's digest, the record stream with the store
first, how a failure is recorded, and how the service holds a run (:class:`Held`)."""

from __future__ import annotations

import contextlib
import hashlib
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.campaign.devices import Devices
from cellcal.campaign.engine import PhaseWatcher
from cellcal.campaign.records import CampaignEnded, CampaignEvent, RecordStream, Subscriber
from cellcal.campaign.store_writer import StoreWriter
from cellcal.config import CellConfig
from cellcal.store.database import Store, StoreError
from cellcal.store.devices import DEVICE_EVENT, device_message


def with_seed(config: CellConfig, seed: int | None) -> CellConfig:
    """The configuration with one seed for the simulated truth, its noise and the plan."""
    if seed is None:
        return config
    return config.model_copy(
        update={
            "simulation": config.simulation.model_copy(update={"seed": seed}),
            "campaign": config.campaign.model_copy(update={"seed": seed}),
        }
    )


def note_devices(stream: RecordStream, campaign_id: int, devices: Devices) -> None:
    """Record which devices the campaign runs with, the robot first: each one's
    description (``store/devices.py``) and, for the report, the line a driver writes
    of its device when it has one (a tracker: identity and air readings)."""
    robot = getattr(devices, "robot", None)  # a holder of sensors alone (a test's) has none
    for device in (robot, *(s.sensor for s in devices.sensors)):
        describe = getattr(device, "describe", None)  # a test double may not describe
        if callable(describe):
            message = device_message(describe())
            stream.emit(CampaignEvent(campaign_id, DEVICE_EVENT, message))
        summary = getattr(device, "summary", None)
        if callable(summary):
            stream.emit(CampaignEvent(campaign_id, DEVICE_EVENT, str(summary())))


def holder(db_path: str) -> str:
    """Who holds a robot's claim during a ``cellcal run``."""
    return f"cellcal run on {Path(db_path).resolve()}"


def config_digest(config: CellConfig) -> str:
    """A short fingerprint of the configuration a campaign runs with."""
    return hashlib.sha256(config.model_dump_json().encode()).hexdigest()[:16]


def record_stream(store: Store, subscribers: Sequence[Subscriber]) -> RecordStream:
    """The campaign's record stream: the store first (critical), then the watchers."""
    stream = RecordStream()
    stream.subscribe(StoreWriter(store), critical=True)
    for subscriber in subscribers:
        stream.subscribe(subscriber)
    return stream


def record_failure(
    stream: RecordStream, campaign_id: int, total: int, message: str, status: str
) -> None:
    """Note a failure and mark the campaign resumable (``interrupted``, or ``paused`` in
    the service) — if the database still takes writes (a full disk may not): the failure
    itself is what the user must see."""
    with contextlib.suppress(StoreError):
        stream.emit(CampaignEvent(campaign_id, "error", message))
    with contextlib.suppress(StoreError):
        stream.emit(CampaignEnded(campaign_id, status, None, total, message))


def _interrupted() -> str:
    return "interrupted"


@dataclass(frozen=True)
class Held:
    """How a campaign runs on devices someone else holds (the service): a hold request
    (deferred pause), the phase watcher (heartbeat, status page), the status a stopped
    acquisition ends in (``paused``, ``aborted``, ``interrupted``: asked when it
    stops), the status a device fault leaves it in, and the hint a failure shows."""

    hold: threading.Event | None = None
    phase: PhaseWatcher | None = None
    halted: Callable[[], str] = _interrupted
    on_fault: str = "interrupted"
    hint: str = ""


def unreachable_text(u: Any) -> str:
    return f"{u.role} pose in {u.region} at {np.round(u.target_mm, 1).tolist()} mm: {u.reason}"
