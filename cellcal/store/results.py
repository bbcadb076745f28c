"""The analysis's tables of the campaign database: registrations, calibrations, fused
positions and reports, an analysis's written in one transaction
(:meth:`AnalysisTables.save_analysis`); and the reads of the service's status (a
campaign's last stored poses). Mixins of :class:`~cellcal.store.database.Store`, which owns
the connection and the transactions; the schema is ``store/schema.py``'s."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cellcal import __version__
from cellcal.calib.geometry import Array
from cellcal.store.connection import loads
from cellcal.store.outbox import OutboxTables
from cellcal.store.schema import COV_COLUMNS, UPPER, utc_now
from cellcal.store.validity import ValidityTables


class _Transaction(Protocol):
    def __enter__(self) -> sqlite3.Connection: ...

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None: ...


@dataclass(frozen=True)
class RegistrationRow:
    """A sensor registered to the robot base with one geometry (``nominal`` or
    ``calibrated``): its ``n`` poses' RMS and maximum residual (mm), ``T_sensor_base``
    and the target offset (mm)."""

    sensor: str
    geometry: str
    n: int
    rms_mm: float
    max_mm: float
    T_sensor_base: Array
    target_offset_mm: Array


@dataclass(frozen=True)
class CalibrationRow:
    """The calibration from the reference sensor: the fit's numbers and the calibrated
    model (TOML)."""

    sensor: str
    n_points: int
    rms_before_mm: float
    rms_after_mm: float
    condition_number: float
    identified: tuple[str, ...]
    unidentifiable: tuple[str, ...]
    model_toml: str


@dataclass(frozen=True)
class FusedRow:
    """One pose's fused position (robot base frame, mm) with its covariance (3×3, mm²),
    the sensors it came from and their agreement (squared Mahalanobis distance)."""

    pose_id: int
    sensors: tuple[str, ...]
    xyz: Array
    cov: Array
    mahalanobis2: float | None


@dataclass(frozen=True)
class AnalysisResults:
    """Everything one analysis of a campaign stores: written whole or not at all
    (:meth:`AnalysisTables.save_analysis`)."""

    campaign_id: int
    registrations: tuple[RegistrationRow, ...]
    calibration: CalibrationRow
    fused: tuple[FusedRow, ...]
    #: the report's summary (a JSON document)
    summary: dict[str, Any]


class AnalysisTables(ValidityTables, OutboxTables):
    """Writes and reads the analysis's results: one analysis in one transaction (stored
    whole or not at all), a report alone in its own."""

    conn: sqlite3.Connection
    path: str
    #: the store's: BEGIN IMMEDIATE … COMMIT (nested: the outer one's)
    transaction: Callable[[], _Transaction]

    def save_analysis(self, results: AnalysisResults) -> None:
        """Store an analysis's registrations, calibration, fused positions, report and
        model (the cell's current one from now) in one transaction: a failure at any of
        them (or a crash) leaves none of them."""
        cid = results.campaign_id
        with self.transaction():
            for r in results.registrations:
                self._insert_registration(cid, r)
            self._insert_calibration(cid, results.calibration)
            for f in results.fused:
                self._insert_fused(cid, f)
            self._insert_report(cid, results.summary)
            self.add_model(cid, results.calibration.model_toml)

    def _insert_registration(self, campaign_id: int, r: RegistrationRow) -> None:
        self.conn.execute(
            """INSERT INTO registrations (campaign_id, sensor, geometry, created, n, rms_mm,
            max_mm, T_sensor_base, target_offset_mm) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            (
                campaign_id,
                r.sensor,
                r.geometry,
                utc_now(),
                r.n,
                r.rms_mm,
                r.max_mm,
                json.dumps(np.asarray(r.T_sensor_base).tolist()),
                json.dumps(np.asarray(r.target_offset_mm).tolist()),
            ),
        )

    def _insert_calibration(self, campaign_id: int, c: CalibrationRow) -> None:
        self.conn.execute(
            """INSERT INTO calibrations (campaign_id, sensor, created, n_points,
            rms_before_mm, rms_after_mm, condition_number, identified, unidentifiable,
            model_toml, cellcal_version) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            (
                campaign_id,
                c.sensor,
                utc_now(),
                c.n_points,
                c.rms_before_mm,
                c.rms_after_mm,
                c.condition_number,
                json.dumps(list(c.identified)),
                json.dumps(list(c.unidentifiable)),
                c.model_toml,
                __version__,
            ),
        )

    def _insert_fused(self, campaign_id: int, f: FusedRow) -> None:
        self.conn.execute(
            f"""INSERT INTO fused (campaign_id, pose_id, created, sensors, x, y, z,
            {", ".join(COV_COLUMNS)}, mahalanobis2)
            VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            (
                campaign_id,
                f.pose_id,
                utc_now(),
                json.dumps(list(f.sensors)),
                *map(float, f.xyz),
                *map(float, f.cov[UPPER]),
                f.mahalanobis2,
            ),
        )

    def _insert_report(self, campaign_id: int, summary: dict[str, Any]) -> None:
        self.conn.execute(
            "INSERT INTO reports (campaign_id, created, summary) VALUES (?, ?, ?)",
            (campaign_id, utc_now(), json.dumps(summary)),
        )

    def add_report(self, campaign_id: int, summary: dict[str, Any]) -> None:
        """A report alone (an ISO 9283 test's), in its own transaction."""
        with self.transaction():
            self._insert_report(campaign_id, summary)

    def latest_report(self, campaign_id: int) -> dict[str, Any] | None:
        row = self.conn.execute(
            "SELECT summary FROM reports WHERE campaign_id = ? ORDER BY id DESC LIMIT 1",
            (campaign_id,),
        ).fetchone()
        if row is None:
            return None
        summary = loads(self.path, row[0], f"campaign {campaign_id}'s report")
        return dict(summary) if isinstance(summary, dict) else {}


class StatusReads:
    """What the service's status shows of a stored campaign (read only)."""

    conn: sqlite3.Connection
    path: str

    def pose_count(self, campaign_id: int) -> int:
        row = self.conn.execute(
            "SELECT COUNT(*) FROM poses WHERE campaign_id = ?", (campaign_id,)
        ).fetchone()
        return int(row[0])

    def stored_by_role(self, campaign_id: int) -> dict[str, int]:
        rows = self.conn.execute(
            "SELECT role, COUNT(*) FROM poses WHERE campaign_id = ? GROUP BY role ORDER BY role",
            (campaign_id,),
        )
        return {str(role): int(n) for role, n in rows}

    def last_event(self, campaign_id: int, kind: str) -> str | None:
        row = self.conn.execute(
            "SELECT message FROM events WHERE campaign_id = ? AND kind = ? ORDER BY id DESC",
            (campaign_id, kind),
        ).fetchone()
        return None if row is None else str(row[0])

    def last_poses(self, campaign_id: int, limit: int) -> list[dict[str, Any]]:
        """The campaign's last ``limit`` stored poses, oldest first, with the event
        stream's ``pose`` keys (``stored``: how many were stored with it; ``retries``: the
        sensors' own and the poses measured again), unrounded (NULL: None)."""
        total = self.pose_count(campaign_id)
        rows = self.conn.execute(
            """SELECT id, idx, role, region, target_x, target_y, target_z, planned_q_deg,
            reached_q_deg, t_end - t_start FROM poses WHERE campaign_id = ?
            ORDER BY id DESC LIMIT ?""",
            (campaign_id, limit),
        ).fetchall()
        asked_again = dict(
            self.conn.execute(
                """SELECT pose_idx, COUNT(*) FROM events WHERE campaign_id = ?
                AND kind = 'sensor-retry' GROUP BY pose_idx""",
                (campaign_id,),
            ).fetchall()
        )
        out = []
        for k, (pid, idx, role, region, x, y, z, planned, reached, seconds) in enumerate(rows):
            stats = self.conn.execute(
                """SELECT sensor, n, mean_x, mean_y, mean_z, std_x, std_y, std_z, retries
                FROM pose_stats WHERE pose_id = ? ORDER BY sensor""",
                (pid,),
            ).fetchall()
            sensors = {
                str(s[0]): {"n": int(s[1]), "mean_mm": list(s[2:5]), "std_mm": list(s[5:8])}
                for s in stats
            }
            out.append(
                {
                    "campaign_id": campaign_id,
                    "idx": int(idx),
                    "role": role,
                    "region": region,
                    "stored": total - k,
                    "target_mm": [x, y, z],
                    "planned_q_deg": loads(self.path, planned, f"pose {idx}'s joints"),
                    "reached_q_deg": loads(self.path, reached, f"pose {idx}'s joints"),
                    "seconds": round(float(seconds), 3),
                    "retries": sum(int(s[8]) for s in stats) + int(asked_again.get(idx, 0)),
                    "sensors": sensors,
                }
            )
        return out[::-1]
