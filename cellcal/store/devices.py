"""The devices a campaign ran with, as its database keeps them: at each start and resume
one ``device`` event per device (the robot, then the sensors in the configuration's
order), its message the JSON object of the device's
:class:`~cellcal.drivers.base.DeviceDescription` —

    {"device": "tracker", "family": "laser-tracker/line-protocol",
     "address": "socket://127.0.0.5:40123", "maker": "cellcal", "model": "mock-tracker",
     "firmware": "1.0", "serial": "SIM-0001", "parts": []}

(null where the device's protocol cannot say; ``parts``: a rig's cameras, described
alike). An events row, so no schema changes: a database of any schema takes them, and
a cellcal that does not know them shows them as events. Beside them, ``device`` events
of text stay what they were: a line a driver writes for the report (a tracker's
identity and air readings), in databases of every age; :func:`description_of` tells
the two apart. In SQL: ``SELECT json_extract(message, '$.serial') FROM events WHERE
kind = 'device' AND json_valid(message)``.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any, Protocol

from cellcal.drivers.base import DeviceDescription

#: The events' kind (the report shows the text ones).
DEVICE_EVENT = "device"


class Events(Protocol):
    """What is read: a campaign's events, oldest first (:meth:`Store.events`)."""

    def events(self, campaign_id: int) -> list[dict[str, Any]]: ...


def device_message(description: DeviceDescription) -> str:
    """The event message of a description: its JSON object (one line)."""
    return json.dumps(asdict(description), ensure_ascii=False)


def description_of(message: str) -> DeviceDescription | None:
    """The description a ``device`` event's message holds; None for one that holds none
    (a line of text, what older cellcals wrote)."""
    if not message.startswith("{"):
        return None
    try:
        data = json.loads(message)
    except ValueError:
        return None
    return _description(data)


def _description(data: Any) -> DeviceDescription | None:
    if not isinstance(data, dict):
        return None
    device, family = data.get("device"), data.get("family")
    if not isinstance(device, str) or not isinstance(family, str):
        return None

    def text(key: str) -> str | None:
        value = data.get(key)
        return value if isinstance(value, str) else None

    listed = data.get("parts")
    parts = [_description(p) for p in listed] if isinstance(listed, list) else []
    return DeviceDescription(
        device,
        family,
        text("address"),
        text("maker"),
        text("model"),
        text("firmware"),
        text("serial"),
        tuple(p for p in parts if p is not None),
    )


def stored_descriptions(store: Events, campaign_id: int) -> list[DeviceDescription]:
    """The devices the campaign last ran with: each device's latest description (a
    resumed campaign has one per start), in the order they were first recorded; empty
    for a campaign recorded before descriptions were."""
    latest: dict[str, DeviceDescription] = {}
    for event in store.events(campaign_id):
        if event["kind"] == DEVICE_EVENT:
            described = description_of(event["message"])
            if described is not None:
                latest[described.device] = described
    return list(latest.values())
