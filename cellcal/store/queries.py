"""The campaign database's reads for the campaign list, the report, the service's queue
and its start-up: a mixin of :class:`~cellcal.store.database.Store`, which owns the
connection. Every answer is typed (a frozen dataclass, a named tuple, numbers); nothing
here writes."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from cellcal.errors import CampaignError


@dataclass(frozen=True)
class CampaignListing:
    """One line of ``cellcal campaign list``."""

    id: int
    created: str
    status: str
    model: str
    sensors: tuple[str, ...]
    n_poses: int
    stored: int
    rms_before_mm: float | None
    rms_after_mm: float | None
    #: the campaign's kind (``calibration``, ``iso9283``), as the campaign layer reads it
    #: from the campaign's events (``campaign/kinds.py``: ``shown_kinds``)
    kind: str = "calibration"

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "created": self.created,
            "status": self.status,
            "kind": self.kind,
            "model": self.model,
            "sensors": list(self.sensors),
            "n_poses": self.n_poses,
            "poses_stored": self.stored,
            "rms_before_mm": self.rms_before_mm,
            "rms_after_mm": self.rms_after_mm,
        }


@dataclass(frozen=True)
class PoseSpan:
    """When a campaign's first and last poses were stored (UTC text), and the first
    one's start and the last one's end on the campaign's clock (s)."""

    first_stored: str
    last_stored: str
    t_start: float
    t_end: float


@dataclass(frozen=True)
class CampaignTimes:
    """When a campaign was created (UTC text), its dwell (s), and the span of its stored
    poses (None: none is stored)."""

    created: str
    dwell_s: float
    poses: PoseSpan | None


class EventRow(NamedTuple):
    """One row of a campaign's events, in the order they were written."""

    time: str
    kind: str
    pose_idx: int | None
    message: str


class CampaignState(NamedTuple):
    id: int
    status: str


#: A pose's target (mm, robot base frame; None where not stored).
Target = tuple[float | None, float | None, float | None]


class CampaignQueries:
    """Reads of the campaigns table and what hangs off it (read only)."""

    conn: sqlite3.Connection
    path: str

    # ------------------------------------------------------------------ campaigns

    def has_campaign(self, campaign_id: int) -> bool:
        row = self.conn.execute("SELECT 1 FROM campaigns WHERE id = ?", (campaign_id,))
        return row.fetchone() is not None

    def latest_campaign_id(self) -> int | None:
        """The newest campaign, whatever its status (None: there is none)."""
        row = self.conn.execute("SELECT MAX(id) FROM campaigns").fetchone()
        return None if row is None or row[0] is None else int(row[0])

    def last_started_campaign(self) -> int | None:
        """The newest campaign that is not only queued (None: there is none)."""
        row = self.conn.execute("SELECT MAX(id) FROM campaigns WHERE status != 'queued'")
        last = row.fetchone()[0]
        return None if last is None else int(last)

    def queued_campaigns(self) -> list[int]:
        """The queue, oldest first."""
        rows = self.conn.execute("SELECT id FROM campaigns WHERE status = 'queued' ORDER BY id")
        return [int(r[0]) for r in rows]

    def oldest_queued(self) -> int | None:
        row = self.conn.execute("SELECT MIN(id) FROM campaigns WHERE status = 'queued'").fetchone()
        return None if row is None or row[0] is None else int(row[0])

    def unfinished_campaigns(self) -> list[CampaignState]:
        """Campaigns left ``running`` or ``paused``, oldest first."""
        rows = self.conn.execute(
            "SELECT id, status FROM campaigns WHERE status IN ('running', 'paused') ORDER BY id"
        ).fetchall()
        return [CampaignState(int(cid), str(status)) for cid, status in rows]

    def last_stopped_by_service(self) -> int | None:
        """The newest ``interrupted`` campaign whose last event is ``service-stopped``."""
        last = self.conn.execute(
            """SELECT c.id FROM campaigns c WHERE c.status = 'interrupted' AND (SELECT kind FROM
            events e WHERE e.campaign_id = c.id ORDER BY e.id DESC LIMIT 1) = 'service-stopped'
            ORDER BY c.id DESC LIMIT 1"""
        ).fetchone()
        return int(last[0]) if last else None

    def campaign_listings(self) -> list[CampaignListing]:
        """Every campaign, oldest first, with its stored poses and its latest report's
        RMS before and after calibration."""
        rows = self.conn.execute(
            """SELECT c.id, c.created, c.status, c.model, c.sensors, c.n_poses,
            (SELECT COUNT(*) FROM poses p WHERE p.campaign_id = c.id),
            (SELECT summary FROM reports r WHERE r.campaign_id = c.id ORDER BY r.id DESC LIMIT 1)
            FROM campaigns c ORDER BY c.id"""
        ).fetchall()
        out = []
        for r in rows:
            summary = json.loads(r[7]) if r[7] else {}
            out.append(
                CampaignListing(
                    id=int(r[0]),
                    created=str(r[1]),
                    status=str(r[2]),
                    model=str(r[3]),
                    sensors=tuple(json.loads(r[4])),
                    n_poses=int(r[5]),
                    stored=int(r[6]),
                    rms_before_mm=summary.get("rms_before_mm"),
                    rms_after_mm=summary.get("rms_after_mm"),
                )
            )
        return out

    def campaign_times(self, campaign_id: int) -> CampaignTimes:
        row = self.conn.execute(
            "SELECT created, dwell_s FROM campaigns WHERE id = ?", (campaign_id,)
        ).fetchone()
        if row is None:
            raise CampaignError(f"{self.path}: no campaign {campaign_id}")
        first, last, t0, t1 = self.conn.execute(
            """SELECT MIN(stored), MAX(stored), MIN(t_start), MAX(t_end) FROM poses
            WHERE campaign_id = ?""",
            (campaign_id,),
        ).fetchone()
        span = None if first is None else PoseSpan(str(first), str(last), t0, t1)
        return CampaignTimes(str(row[0]), float(row[1]), span)

    # ------------------------------------------------------------------ what hangs off one

    def has_event(self, campaign_id: int, kind: str) -> bool:
        row = self.conn.execute(
            "SELECT 1 FROM events WHERE campaign_id = ? AND kind = ? LIMIT 1", (campaign_id, kind)
        ).fetchone()
        return row is not None

    def first_events(
        self, kinds: Sequence[str], campaign_id: int | None = None
    ) -> dict[int, dict[str, str]]:
        """Per campaign that has any (every one, or ``campaign_id``'s alone), the message
        of its first event of each of ``kinds``: ``{campaign id: {kind: message}}``."""
        marks = ", ".join("?" * len(kinds))
        one = "" if campaign_id is None else " AND campaign_id = ?"
        rows = self.conn.execute(
            f"""SELECT campaign_id, kind, message FROM events WHERE id IN (SELECT MIN(id)
            FROM events WHERE kind IN ({marks}){one} GROUP BY campaign_id, kind)""",
            (*kinds, *(() if campaign_id is None else (campaign_id,))),
        )
        out: dict[int, dict[str, str]] = {}
        for cid, kind, message in rows:
            out.setdefault(int(cid), {})[str(kind)] = str(message)
        return out

    def event_rows(self, campaign_id: int) -> tuple[EventRow, ...]:
        rows = self.conn.execute(
            "SELECT time, kind, pose_idx, message FROM events WHERE campaign_id = ? ORDER BY id",
            (campaign_id,),
        )
        return tuple(
            EventRow(str(t), str(k), None if i is None else int(i), str(msg))
            for t, k, i, msg in rows
        )

    def pose_targets(self, campaign_id: int) -> dict[int, Target]:
        """Each stored pose's target, by plan index."""
        rows = self.conn.execute(
            "SELECT idx, target_x, target_y, target_z FROM poses WHERE campaign_id = ?",
            (campaign_id,),
        )
        return {int(i): (x, y, z) for i, x, y, z in rows}

    def retries_by_sensor(self, campaign_id: int) -> dict[str, int]:
        """Per sensor, the retries of all its stored poses."""
        rows = self.conn.execute(
            """SELECT s.sensor, SUM(s.retries) FROM pose_stats s JOIN poses p ON p.id = s.pose_id
            WHERE p.campaign_id = ? GROUP BY s.sensor""",
            (campaign_id,),
        )
        return {str(s): int(n) for s, n in rows}

    def latest_model_toml(self, campaign_id: int) -> str | None:
        """The calibrated model (TOML) of the campaign's latest calibration; None: none."""
        row = self.conn.execute(
            "SELECT model_toml FROM calibrations WHERE campaign_id = ? ORDER BY id DESC LIMIT 1",
            (campaign_id,),
        ).fetchone()
        return None if row is None else str(row[0])
