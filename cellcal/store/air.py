"""The air each sample was measured in, as the campaign database keeps it (schema 5:
``samples.temperature_c``, ``pressure_hpa``, ``humidity_pct``, written for a tracker that
reports the air it compensated with — an emScon tracker's meteo), read for the report;
and the robot's joint temperatures at each pose (``robot-temperature`` events), read for
the error terms."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.store.schema import METEO_COLUMNS


@dataclass(frozen=True)
class AirRange:
    """One sensor's air over a campaign: how many samples carry it, and the lowest and
    highest temperature (°C), pressure (hPa) and humidity (%RH)."""

    sensor: str
    n: int
    low: tuple[float, float, float]
    high: tuple[float, float, float]


class AirReads:
    """The store's reads of the samples' air and the robot's temperatures (a mixin of
    :class:`~cellcal.store.database.Store`)."""

    conn: sqlite3.Connection

    def air_ranges(self, campaign_id: int) -> tuple[AirRange, ...]:
        """Per sensor that reported it, the range of the air its samples were taken in
        (none from a file older than schema 5, opened read-only)."""
        columns = {str(r[1]) for r in self.conn.execute("PRAGMA table_info(samples)")}
        if not set(METEO_COLUMNS) <= columns:
            return ()
        lows = ", ".join(f"MIN(s.{c})" for c in METEO_COLUMNS)
        highs = ", ".join(f"MAX(s.{c})" for c in METEO_COLUMNS)
        rows = self.conn.execute(
            f"""SELECT s.sensor, COUNT(*), {lows}, {highs} FROM samples s
            JOIN poses p ON p.id = s.pose_id
            WHERE p.campaign_id = ? AND s.temperature_c IS NOT NULL
            GROUP BY s.sensor ORDER BY s.sensor""",
            (campaign_id,),
        ).fetchall()
        return tuple(
            AirRange(str(r[0]), int(r[1]), (r[2], r[3], r[4]), (r[5], r[6], r[7])) for r in rows
        )

    def robot_temperatures(self, campaign_id: int, idx: list[int]) -> Array | None:
        """Each pose's mean joint temperature (°C) from its ``robot-temperature`` event;
        None when no pose has one (a robot whose driver reads none)."""
        rows = self.conn.execute(
            """SELECT pose_idx, message FROM events WHERE campaign_id = ?
            AND kind = 'robot-temperature' ORDER BY id""",
            (campaign_id,),
        ).fetchall()
        if not rows:
            return None
        by_idx: dict[int, float] = {}
        for pose_idx, message in rows:
            try:
                joints = [float(v) for v in json.loads(message)["joints_c"]]
            except (ValueError, KeyError, TypeError):
                continue  # a damaged row: that pose has none
            if pose_idx is not None and joints:
                by_idx[int(pose_idx)] = float(np.mean(joints))
        return np.array([by_idx.get(i, np.nan) for i in idx])
