"""The campaign database (SQLite through sqlite-utils): append-only, crash-safe.

The core is public (``docs/database.md``): ``campaigns``, ``poses`` (``idx``
unique within a campaign, planned and reached joints), ``samples`` (``pose_id``,
``sensor``, host and device timestamps, ``x, y, z``). Other tools read it directly.

Rules that make a SIGKILL at any moment harmless:

* a pose, its raw samples and its statistics are written in one transaction — after a
  crash the pose is either wholly there or not there, and a resumed campaign redoes
  exactly the poses that are not there;
* ``UNIQUE(campaign_id, idx)`` makes storing a pose twice impossible;
* WAL journal with ``synchronous=FULL``: a committed pose survives a crash of the
  process and of the machine;
* nothing is updated in place but a campaign's ``status`` and ``finished`` time, a
  model's end (``valid_until``, ``ended_by``) and the fleet's marks of what it sent; a
  rerun is a new campaign.

sqlite-utils opens the file and runs the migrations; the pose write goes through the
same connection with explicit ``BEGIN IMMEDIATE``/``COMMIT`` (``executemany`` of the
samples), because sqlite-utils' own ``insert_all`` commits by itself and would split
the pose's transaction.

The schema version is SQLite's ``user_version``; :data:`MIGRATIONS` bring an older file
up to date when it is opened (schema 1 held the acquisition only; 2 added the analysis
tables).

What is no campaign database is refused when it is opened, in one line naming the file
(``store_connection``, ``store_schema``): a path that cannot be a database file (empty,
``:memory:``, a URI), a file that is not SQLite, a ``user_version`` that is not a
cellcal schema or does not fit the tables, a table or column missing, a damaged page
(``PRAGMA quick_check``, about a second a gigabyte); nothing is written to a file that
is refused. Damage met later, wherever a statement runs, is one such line too.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import sqlite_utils

from cellcal import __version__
from cellcal.calib.geometry import Array
from cellcal.drivers.base import Series
from cellcal.errors import CampaignError
from cellcal.store.air import AirReads
from cellcal.store.connection import (
    StoreError,
    Transaction,
    damaged,
    database_path,
    loads,
    open_reader,
    open_writer,
    writing,
)
from cellcal.store.queries import CampaignQueries
from cellcal.store.results import AnalysisTables, StatusReads
from cellcal.store.schema import (
    COV_COLUMNS,
    METEO_COLUMNS,
    MIGRATIONS,
    SAMPLE_COLUMNS,
    SCHEMA_VERSION,
    UPPER,
    floats,
    schema_problem,
    sql_value,
    symmetric,
    utc_now,
)

__all__ = [
    "MIGRATIONS",
    "SCHEMA_VERSION",
    "CampaignRow",
    "PoseData",
    "Store",
    "StoreError",
    "database_path",
]


@dataclass(frozen=True)
class CampaignRow:
    id: int
    status: str
    mock: bool
    seed: int | None
    time_scale: float | None
    model: str
    sensors: tuple[str, ...]
    n_poses: int
    samples_per_pose: int
    plan_digest: str
    config_json: str
    config_path: str | None


@dataclass(frozen=True)
class PoseData:
    """Everything stored about a campaign's poses, as arrays in plan order: ``idx``,
    ``role``, ``region``, reached joints (rad), and per sensor the mean position, its
    standard deviation, the sample count and the mean's covariance."""

    idx: Array
    role: tuple[str, ...]
    region: tuple[str, ...]
    q: Array
    mean: dict[str, Array]
    std: dict[str, Array]
    n: dict[str, Array]
    #: per sensor, the covariance of each pose's mean (N×3×3, mm²; NaN where the sensor
    #: gave none, or measured nothing at that pose)
    cov: dict[str, Array]
    #: the poses' row ids
    pose_id: Array
    #: each pose's time (s since the campaign's first sample; NaN for a pose without
    #: samples) and the air temperature its tracker reported (°C; NaN where none did)
    time_s: Array | None = None
    temperature_c: Array | None = None
    #: each pose's mean joint temperature, where the robot reports them (°C; NaN for a
    #: pose without; None: none has)
    robot_temperature_c: Array | None = None
    #: each pose's payload (kg): not stored, but planned (``[campaign] payloads_kg``);
    #: set by whoever knows the plan (None: not planned)
    payload_kg: Array | None = None

    def measured(self, sensor: str) -> Array:
        """Which poses this sensor measured (a boolean mask)."""
        if sensor not in self.mean:
            return np.zeros(len(self.idx), dtype=bool)
        return np.asarray(np.isfinite(self.mean[sensor]).all(axis=1))


class Store(AnalysisTables, StatusReads, CampaignQueries, AirReads):
    """One campaign database file (the analysis's tables: :class:`AnalysisTables`; the
    status's reads: :class:`StatusReads`; the campaign list's, the report's and the
    queue's reads: :class:`CampaignQueries`; the samples' air: :class:`AirReads`; the
    models' validity and the checks: ``ValidityTables``, the analysis tables' base)."""

    def __init__(self, path: str | Path, *, readonly: bool = False) -> None:
        self.path = database_path(path)
        self.readonly = readonly
        self._wal = False
        conn = open_reader(self.path) if readonly else open_writer(self.path)
        try:
            self.conn = conn
            self.db = sqlite_utils.Database(conn)
            self._verify()
        except BaseException:
            conn.close()
            raise

    def _verify(self) -> None:
        """Refuse a file that is no cellcal database of a schema this cellcal reads, or
        a damaged one (one line saying what it is); a writer then switches it to WAL and
        brings an older schema up to date. Nothing is written to a file that is refused."""
        version = self.schema_version
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"{self.path}: schema version {version} is newer than this cellcal "
                f"understands ({SCHEMA_VERSION}); upgrade cellcal"
            )
        names = self.conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
        tables = {
            str(name): {
                str(r[0])
                for r in self.conn.execute("SELECT name FROM pragma_table_info(?)", (name,))
            }
            for (name,) in names.fetchall()
        }
        problem = schema_problem(tables, version)
        if problem is None and self.readonly and version == 0:
            problem = "not a cellcal database (an empty SQLite file)"
        if problem is not None:
            raise StoreError(f"{self.path}: {problem}")
        # Every page, before a reader trusts the file or a writer adds to it: about a
        # second for a gigabyte.
        check = self.conn.execute("PRAGMA quick_check(1)").fetchone()
        if check is None or check[0] != "ok":
            detail = " ".join(str(check[0] if check else "no answer").split())
            detail = detail.removeprefix("*** in database main *** ")
            raise StoreError(f"{self.path}: {damaged(self.path, detail)}")
        if self.readonly:
            return
        with writing():
            self.conn.execute("PRAGMA journal_mode=WAL")
            self._wal = True
            self.conn.execute("PRAGMA synchronous=FULL")
            self.conn.execute("PRAGMA foreign_keys=ON")
        self.migrate(version)

    def migrate(self, version: int) -> None:
        for v in range(version, SCHEMA_VERSION):
            with self.transaction():
                MIGRATIONS[v](self.db)
                self.conn.execute(f"PRAGMA user_version = {v + 1}")

    def transaction(self) -> Transaction:
        return Transaction(self.conn)

    def close(self) -> None:
        """Close; a writer leaves the file in rollback-journal mode when it is the last
        connection, so that a user who may not write the folder can still read it (a WAL
        database needs its -shm file, which such a reader cannot create)."""
        if self._wal:
            # Another open connection keeps it WAL until the last one closes.
            with contextlib.suppress(sqlite3.Error, StoreError):
                self.conn.execute("PRAGMA journal_mode=DELETE")
        self.conn.close()

    @property
    def schema_version(self) -> int:
        return int(self.conn.execute("PRAGMA user_version").fetchone()[0])

    # ------------------------------------------------------------------ campaigns

    def create_campaign(
        self,
        *,
        config_json: str,
        config_path: str | None,
        mock: bool,
        seed: int | None,
        time_scale: float | None,
        model: str,
        sensors: Iterable[str],
        n_poses: int,
        samples_per_pose: int,
        dwell_s: float,
        plan_digest: str,
        status: str = "running",
        kind: str = "calibration",
    ) -> int:
        with self.transaction():
            cur = self.conn.execute(
                """INSERT INTO campaigns (created, status, mock, seed, time_scale, model,
                sensors, n_poses, samples_per_pose, dwell_s, plan_digest, config_path,
                config_json, cellcal_version, kind)
                VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
                (
                    utc_now(),
                    status,
                    int(mock),
                    seed,
                    time_scale,
                    model,
                    json.dumps(list(sensors)),
                    n_poses,
                    samples_per_pose,
                    dwell_s,
                    plan_digest,
                    config_path,
                    config_json,
                    __version__,
                    kind,
                ),
            )
            return int(cur.lastrowid or 0)

    def acquired_with(self, campaign_id: int) -> str | None:
        """The cellcal version that acquired the campaign; None where it is not recorded
        (a campaign an older cellcal wrote, or a file of schema 3 or older read as it is)."""
        if self.schema_version < 4:
            return None
        row = self.conn.execute(
            "SELECT cellcal_version FROM campaigns WHERE id = ?", (campaign_id,)
        ).fetchone()
        return None if row is None else row[0]

    def campaign(self, campaign_id: int) -> CampaignRow:
        row = self.conn.execute(
            """SELECT id, status, mock, seed, time_scale, model, sensors, n_poses,
            samples_per_pose, plan_digest, config_json, config_path FROM campaigns
            WHERE id = ?""",
            (campaign_id,),
        ).fetchone()
        if row is None:
            raise CampaignError(f"{self.path}: no campaign {campaign_id}")
        return CampaignRow(
            id=row[0],
            status=row[1],
            mock=bool(row[2]),
            seed=row[3],
            time_scale=row[4],
            model=row[5],
            sensors=tuple(loads(self.path, row[6], f"campaign {campaign_id}'s sensors")),
            n_poses=row[7],
            samples_per_pose=row[8],
            plan_digest=row[9],
            config_json=row[10],
            config_path=row[11],
        )

    def set_status(self, campaign_id: int, status: str) -> None:
        finished = utc_now() if status in ("complete", "failed", "refused", "aborted") else None
        with self.transaction():
            self.conn.execute(
                "UPDATE campaigns SET status = ?, finished = ? WHERE id = ?",
                (status, finished, campaign_id),
            )

    # ------------------------------------------------------------------ poses

    def last_pose_time(self, campaign_id: int) -> float:
        """The latest ``t_end`` stored (host clock), 0 if none: a resumed simulated clock
        continues from there."""
        row = self.conn.execute(
            "SELECT MAX(t_end) FROM poses WHERE campaign_id = ?", (campaign_id,)
        ).fetchone()
        return float(row[0]) if row and row[0] is not None else 0.0

    def completed_indices(self, campaign_id: int) -> set[int]:
        rows = self.conn.execute("SELECT idx FROM poses WHERE campaign_id = ?", (campaign_id,))
        return {int(r[0]) for r in rows}

    def add_pose(
        self,
        campaign_id: int,
        *,
        idx: int,
        role: str,
        region: str,
        target_mm: Array,
        planned_q: Array,
        reached_q: Array,
        t_start: float,
        t_end: float,
        series: Iterable[Series],
    ) -> int:
        """Store a pose, all its samples and their statistics atomically."""
        series = list(series)
        try:
            with self.transaction():
                cur = self.conn.execute(
                    """INSERT INTO poses (campaign_id, idx, role, region, target_x, target_y,
                    target_z, planned_q_deg, reached_q_deg, t_start, t_end, stored)
                    VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
                    (
                        campaign_id,
                        idx,
                        role,
                        region,
                        *(float(v) for v in target_mm),
                        json.dumps([round(float(v), 9) for v in np.degrees(planned_q)]),
                        json.dumps([round(float(v), 9) for v in np.degrees(reached_q)]),
                        t_start,
                        t_end,
                        utc_now(),
                    ),
                )
                pose_id = int(cur.lastrowid or 0)
                for s in series:
                    self._add_series(pose_id, s)
        except sqlite3.IntegrityError as exc:
            raise CampaignError(
                f"campaign {campaign_id}: pose {idx} is already stored ({exc})"
            ) from None
        return pose_id

    def _add_series(self, pose_id: int, s: Series) -> None:
        """A series' samples (with their covariances and orientations when it has them)
        and its statistics; inside the pose's transaction."""
        n = s.n
        cov = s.cov[:, UPPER[0], UPPER[1]] if s.cov is not None else np.full((n, 6), np.nan)
        ori = s.orientation if s.orientation is not None else np.full((n, 4), np.nan)
        air = s.meteo if s.meteo is not None else np.full((n, 3), np.nan)
        table = np.column_stack([s.host_time, s.device_time, s.xyz, cov, ori, air]).tolist()
        columns = ", ".join((*SAMPLE_COLUMNS, *METEO_COLUMNS))
        marks = ", ".join("?" * (len(SAMPLE_COLUMNS) + len(METEO_COLUMNS) + 1))
        self.conn.executemany(
            f"INSERT INTO samples (pose_id, sensor, {columns}) VALUES (?, {marks})",
            [(pose_id, s.sensor, *map(sql_value, row)) for row in table],
        )
        mc = s.mean_covariance
        mean_cov = mc[UPPER] if mc is not None else np.full(6, np.nan)
        self.conn.execute(
            f"""INSERT INTO pose_stats (pose_id, sensor, n, mean_x, mean_y, mean_z,
            std_x, std_y, std_z, retries, {", ".join(COV_COLUMNS)})
            VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            (
                pose_id,
                s.sensor,
                n,
                *map(sql_value, s.mean if n else np.full(3, np.nan)),
                *map(sql_value, s.std),
                s.retries,
                *map(sql_value, mean_cov),
            ),
        )

    def add_event(
        self, campaign_id: int, kind: str, message: str, pose_idx: int | None = None
    ) -> None:
        with self.transaction():
            self.conn.execute(
                """INSERT INTO events (campaign_id, time, kind, pose_idx, message)
                VALUES (?, ?, ?, ?, ?)""",
                (campaign_id, utc_now(), kind, pose_idx, message),
            )

    def events(self, campaign_id: int) -> list[dict[str, Any]]:
        rows = self.conn.execute(
            "SELECT time, kind, pose_idx, message FROM events WHERE campaign_id = ? ORDER BY id",
            (campaign_id,),
        )
        return [dict(zip(("time", "kind", "pose_idx", "message"), r, strict=True)) for r in rows]

    def pose_data(self, campaign_id: int) -> PoseData:
        poses = self.conn.execute(
            """SELECT id, idx, role, region, reached_q_deg FROM poses WHERE campaign_id = ?
            ORDER BY idx""",
            (campaign_id,),
        ).fetchall()
        ids = [p[0] for p in poses]
        pos = {pid: k for k, pid in enumerate(ids)}
        mean: dict[str, Array] = {}
        std: dict[str, Array] = {}
        n: dict[str, Array] = {}
        cov: dict[str, Array] = {}
        stats = self.conn.execute(
            f"""SELECT s.pose_id, s.sensor, s.n, s.mean_x, s.mean_y, s.mean_z, s.std_x, s.std_y,
            s.std_z, {self._pose_stats_cov()}
            FROM pose_stats s JOIN poses p ON p.id = s.pose_id WHERE p.campaign_id = ?""",
            (campaign_id,),
        )
        for pid, sensor, cnt, mx, my, mz, sx, sy, sz, *c in stats:
            if sensor not in mean:
                mean[sensor] = np.full((len(ids), 3), np.nan)
                std[sensor] = np.full((len(ids), 3), np.nan)
                n[sensor] = np.zeros(len(ids))
                cov[sensor] = np.full((len(ids), 3, 3), np.nan)
            k = pos[pid]
            mean[sensor][k] = floats((mx, my, mz))
            std[sensor][k] = floats((sx, sy, sz))
            n[sensor][k] = cnt
            cov[sensor][k] = symmetric(floats(c))
        time_s = np.full(len(ids), np.nan)
        temperature_c = np.full(len(ids), np.nan)
        air = "AVG(s.temperature_c)" if self.schema_version >= 5 else "NULL"
        for pid, t, c in self.conn.execute(
            f"""SELECT s.pose_id, AVG(s.host_time), {air} FROM samples s
            JOIN poses p ON p.id = s.pose_id WHERE p.campaign_id = ? GROUP BY s.pose_id""",
            (campaign_id,),
        ):
            time_s[pos[pid]] = t if t is not None else np.nan
            temperature_c[pos[pid]] = c if c is not None else np.nan
        if np.isfinite(time_s).any():
            time_s -= np.nanmin(time_s)
        robot_c = self.robot_temperatures(campaign_id, [int(p[1]) for p in poses])
        reached = [loads(self.path, p[4], f"pose {p[1]}'s joints") for p in poses]
        q = np.radians(np.array(reached, dtype=np.float64)) if poses else np.zeros((0, 0))
        return PoseData(
            idx=np.array([p[1] for p in poses], dtype=int),
            role=tuple(p[2] for p in poses),
            region=tuple(p[3] for p in poses),
            q=q,
            mean=mean,
            std=std,
            n=n,
            cov=cov,
            pose_id=np.array(ids, dtype=int),
            time_s=time_s,
            temperature_c=temperature_c,
            robot_temperature_c=robot_c,
        )

    def _pose_stats_cov(self) -> str:
        """The covariance columns of ``pose_stats``: NULLs in a file older than schema 3
        opened read-only (which cannot be migrated)."""
        if self.schema_version < 3:
            return ", ".join("NULL" for _ in COV_COLUMNS)
        return ", ".join(f"s.{c}" for c in COV_COLUMNS)
