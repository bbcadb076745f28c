"""The record stream: what a campaign did, as it happens, for everything that watches.

A campaign emits four kinds of record (bluesky's "documents"): it started (the plan, the
configuration's digest, how many poses were already stored), a pose was stored (where
the robot went, each sensor's series and statistics, the retries it took), an event
(a sensor retry, a device fault, an unreachable pose, a stop request) and it ended (its
status and, when complete, the summary). The store, the progress display and any later
watcher (the service's event stream, its status page) subscribe to the same stream;
nothing polls the database to learn what the engine did.

A subscriber that raises is logged and dropped, and the acquisition goes on — except a
*critical* one: the store. A pose the store could not write must not be counted as
measured, so its failure ends the campaign (resumable, nothing lost) as before.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Union

from cellcal.calib.geometry import Array
from cellcal.campaign.plan import Plan, PlannedPose
from cellcal.drivers.base import Series

if TYPE_CHECKING:
    from cellcal.campaign.analysis import CampaignSummary

log = logging.getLogger("cellcal.records")


@dataclass(frozen=True)
class CampaignStarted:
    """A campaign (of ``kind``, ``kinds.py``) starts, or resumes with ``done`` poses
    already stored."""

    campaign_id: int
    plan: Plan
    config_digest: str
    done: int
    resumed: bool
    t: float
    kind: str = "calibration"

    @property
    def total(self) -> int:
        return len(self.plan.poses)


@dataclass(frozen=True)
class SensorStatistics:
    """One sensor's series at a pose: its mean and sample standard deviation (mm)."""

    sensor: str
    n: int
    mean: Array
    std: Array
    retries: int


@dataclass(frozen=True)
class PoseStored:
    """A pose and its samples, as the store is asked to keep them."""

    campaign_id: int
    pose: PlannedPose
    reached_q: Array
    series: tuple[Series, ...]
    t_start: float
    t_end: float
    retries: int
    done: int
    total: int

    @property
    def statistics(self) -> tuple[SensorStatistics, ...]:
        return tuple(SensorStatistics(s.sensor, s.n, s.mean, s.std, s.retries) for s in self.series)


@dataclass(frozen=True)
class CampaignEvent:
    """Something worth knowing that is not a pose: ``kind`` is one word
    (``sensor-retry``, ``device-error``, ``unreachable``, ``stop-requested``, ...)."""

    campaign_id: int
    kind: str
    message: str
    pose_idx: int | None = None
    t: float | None = None


@dataclass(frozen=True)
class CampaignEnded:
    """The campaign stopped: ``status`` is ``complete``, ``interrupted`` (resumable) or
    ``refused`` (every sample stored, the result not accepted)."""

    campaign_id: int
    status: str
    stored: int | None  # None: unknown (the store failed)
    total: int
    message: str
    summary: CampaignSummary | None = None


Record = Union[CampaignStarted, PoseStored, CampaignEvent, CampaignEnded]  # noqa: UP007
Subscriber = Callable[[Record], None]


class RecordStream:
    """Fan records out to subscribers, in the order they subscribed; thread-safe."""

    def __init__(self) -> None:
        self._subscribers: list[tuple[Subscriber, bool]] = []
        self._lock = threading.Lock()
        self.dropped: list[str] = []  # subscribers dropped after a failure, and why

    def subscribe(self, subscriber: Subscriber, *, critical: bool = False) -> Callable[[], None]:
        """Add a subscriber; the returned function removes it. A critical subscriber's
        exception propagates to the emitter (it ends the acquisition)."""
        entry = (subscriber, critical)
        with self._lock:
            self._subscribers.append(entry)

        def unsubscribe() -> None:
            with self._lock:
                if entry in self._subscribers:
                    self._subscribers.remove(entry)

        return unsubscribe

    def emit(self, record: Record) -> None:
        """Hand the record to every subscriber; then re-raise the first failure of a
        critical one (the others have seen the record all the same)."""
        with self._lock:
            subscribers = list(self._subscribers)
        failure: Exception | None = None
        for subscriber, critical in subscribers:
            try:
                subscriber(record)
            except Exception as exc:
                if critical:
                    failure = failure or exc
                    continue
                why = f"{_name(subscriber)}: {type(exc).__name__}: {exc}"
                log.warning("record subscriber dropped after a failure: %s", why)
                self.dropped.append(why)
                with self._lock:
                    if (subscriber, critical) in self._subscribers:
                        self._subscribers.remove((subscriber, critical))
        if failure is not None:
            raise failure


def _name(subscriber: Subscriber) -> str:
    return getattr(subscriber, "__qualname__", type(subscriber).__name__)
