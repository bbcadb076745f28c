"""The service's pieces in the test's own process, for the tests that need no twin: a
campaign's row written through the store (no plan run), and the control API's service
(``api.Service``) around a store, a control object and an event hub."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from cellcal.service.api import EventHub, Service
from cellcal.service.control import Control
from cellcal.store.database import Store
from tests.conftest import tracker_cell


def campaign_row(
    store: Store,
    *,
    n_poses: int = 10,
    sensors: Sequence[str] = ("tracker",),
    status: str = "running",
    **more: Any,
) -> int:
    """A campaign's row as ``create_campaign`` writes it, of the KR 5 arc in mock mode
    (seed 1, as fast as it goes, 20 samples per pose, 7 s dwell, no configuration or plan
    of its own); ``more``: other columns. Its id."""
    columns: dict[str, Any] = {
        "config_json": "{}",
        "config_path": None,
        "mock": True,
        "seed": 1,
        "time_scale": 0.0,
        "model": "kuka-kr5-arc",
        "sensors": list(sensors),
        "n_poses": n_poses,
        "samples_per_pose": 20,
        "dwell_s": 7.0,
        "plan_digest": "0" * 16,
        "status": status,
    }
    return store.create_campaign(**(columns | more))


def service_of(store: Store, control: Control, hub: EventHub, sock: str) -> Service:
    """What the control API's handlers need, as the service makes it: the tracker cell in
    mock mode, listening on ``sock`` (no status page), for the caller's group."""
    return Service(
        control=control,
        store=store,
        hub=hub,
        config=tracker_cell(),
        config_path=None,
        mock=True,
        time_scale=0.0,
        socket_path=sock,
        http=None,
        group_id=os.getgid(),
    )
