"""The campaign database's schema: one function per version, applied in order.

The version is SQLite's ``user_version``: schema 1 holds the acquisition (``campaigns``,
``poses``, ``samples``, ``events``), schema 2 adds the analysis (``registrations``,
``calibrations``, ``reports``), schema 3 adds each sample's covariance and orientation,
the covariance of each pose's mean, and the fused positions (``fused``), schema 4 the
cellcal version that created each campaign and made each calibration
(``cellcal_version``; NULL in rows an older cellcal wrote), schema 5 each sample's air,
schema 6 each campaign's ``kind``, the models with their validity (``models``) and the
checks between calibrations (``checks``), schema 7 the fleet's outbox (``outbox``,
filled by triggers: a campaign that ended, a model made or ended) and what was sent
(``fleet_sent``, ``fleet_state``).
:data:`MIGRATIONS` [v] brings a file from version v to v + 1; ``cellcal.store.database``
runs them when it opens an older file. The core tables
and columns are public (``docs/database.md``) and are never renamed.
"""

from __future__ import annotations

import functools
import hashlib
import sqlite3
from collections.abc import Callable, Iterable
from datetime import UTC, datetime

import numpy as np
import sqlite_utils

from cellcal.calib.geometry import Array

SCHEMA_VERSION = 7

#: A symmetric 3×3 covariance (mm²) as six columns.
COV_COLUMNS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
#: A unit quaternion (w, x, y, z) as four columns.
ORI_COLUMNS = ("ori_w", "ori_x", "ori_y", "ori_z")

#: the sample columns after (pose_id, sensor), in the order the store writes them
SAMPLE_COLUMNS = ("host_time", "device_time", "x", "y", "z", *COV_COLUMNS, *ORI_COLUMNS)
#: The air a tracker compensated a sample with (°C, hPa, %RH); NULL where the sensor does
#: not report it (schema 5).
METEO_COLUMNS = ("temperature_c", "pressure_hpa", "humidity_pct")
#: the upper triangle of a 3×3 matrix in COV_COLUMNS' order
UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def utc_now() -> str:
    """A row's time stamp: UTC, ISO 8601, milliseconds."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def sql_value(v: float) -> float | None:
    """NaN is NULL in the database."""
    return None if v != v else float(v)


def floats(values: Iterable[float | None]) -> Array:
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


def symmetric(upper: Array) -> Array:
    out = np.empty((3, 3))
    out[UPPER] = upper
    out[UPPER[1], UPPER[0]] = upper
    return out


def _schema_1(db: sqlite_utils.Database) -> None:
    db.execute(
        """CREATE TABLE campaigns (
            id INTEGER PRIMARY KEY,
            created TEXT NOT NULL,
            status TEXT NOT NULL,
            mock INTEGER NOT NULL,
            seed INTEGER,
            time_scale REAL,
            model TEXT NOT NULL,
            sensors TEXT NOT NULL,
            n_poses INTEGER NOT NULL,
            samples_per_pose INTEGER NOT NULL,
            dwell_s REAL NOT NULL,
            plan_digest TEXT NOT NULL,
            config_path TEXT,
            config_json TEXT NOT NULL
        )"""
    )
    db.execute(
        """CREATE TABLE poses (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            idx INTEGER NOT NULL,
            role TEXT NOT NULL,
            region TEXT NOT NULL,
            target_x REAL, target_y REAL, target_z REAL,
            planned_q_deg TEXT NOT NULL,
            reached_q_deg TEXT NOT NULL,
            t_start REAL NOT NULL,
            t_end REAL NOT NULL,
            stored TEXT NOT NULL,
            UNIQUE (campaign_id, idx)
        )"""
    )
    db.execute(
        """CREATE TABLE samples (
            id INTEGER PRIMARY KEY,
            pose_id INTEGER NOT NULL REFERENCES poses(id),
            sensor TEXT NOT NULL,
            host_time REAL NOT NULL,
            device_time REAL NOT NULL,
            x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL
        )"""
    )
    db.execute("CREATE INDEX samples_pose ON samples (pose_id, sensor)")
    db.execute(
        """CREATE TABLE pose_stats (
            pose_id INTEGER NOT NULL REFERENCES poses(id),
            sensor TEXT NOT NULL,
            n INTEGER NOT NULL,
            mean_x REAL, mean_y REAL, mean_z REAL,
            std_x REAL, std_y REAL, std_z REAL,
            retries INTEGER NOT NULL,
            PRIMARY KEY (pose_id, sensor)
        )"""
    )
    db.execute(
        """CREATE TABLE events (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            time TEXT NOT NULL,
            kind TEXT NOT NULL,
            pose_idx INTEGER,
            message TEXT NOT NULL
        )"""
    )


def _schema_2(db: sqlite_utils.Database) -> None:
    db.execute("ALTER TABLE campaigns ADD COLUMN finished TEXT")
    db.execute(
        """CREATE TABLE registrations (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            sensor TEXT NOT NULL,
            geometry TEXT NOT NULL,
            created TEXT NOT NULL,
            n INTEGER NOT NULL,
            rms_mm REAL NOT NULL,
            max_mm REAL NOT NULL,
            T_sensor_base TEXT NOT NULL,
            target_offset_mm TEXT NOT NULL
        )"""
    )
    db.execute(
        """CREATE TABLE calibrations (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            sensor TEXT NOT NULL,
            created TEXT NOT NULL,
            n_points INTEGER NOT NULL,
            rms_before_mm REAL NOT NULL,
            rms_after_mm REAL NOT NULL,
            condition_number REAL NOT NULL,
            identified TEXT NOT NULL,
            unidentifiable TEXT NOT NULL,
            model_toml TEXT NOT NULL
        )"""
    )
    db.execute(
        """CREATE TABLE reports (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            created TEXT NOT NULL,
            summary TEXT NOT NULL
        )"""
    )


def _schema_3(db: sqlite_utils.Database) -> None:
    # NULL where a sensor gives no covariance or orientation (the tracker; old rows)
    for column in (*COV_COLUMNS, *ORI_COLUMNS):
        db.execute(f"ALTER TABLE samples ADD COLUMN {column} REAL")
    for column in COV_COLUMNS:
        db.execute(f"ALTER TABLE pose_stats ADD COLUMN {column} REAL")
    cov = ", ".join(f"{c} REAL NOT NULL" for c in COV_COLUMNS)
    db.execute(
        f"""CREATE TABLE fused (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            pose_id INTEGER NOT NULL REFERENCES poses(id),
            created TEXT NOT NULL,
            sensors TEXT NOT NULL,
            x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL,
            {cov},
            mahalanobis2 REAL
        )"""
    )
    db.execute("CREATE INDEX fused_pose ON fused (pose_id)")


def _schema_4(db: sqlite_utils.Database) -> None:
    # which cellcal acquired a campaign and which analysed it: a report is only as good
    # as the code that made it
    db.execute("ALTER TABLE campaigns ADD COLUMN cellcal_version TEXT")
    db.execute("ALTER TABLE calibrations ADD COLUMN cellcal_version TEXT")


def _schema_5(db: sqlite_utils.Database) -> None:
    # each sample's air, as the tracker that measured it compensated with it (emScon)
    for column in METEO_COLUMNS:
        db.execute(f"ALTER TABLE samples ADD COLUMN {column} REAL")


def _schema_6(db: sqlite_utils.Database) -> None:
    # what each campaign is (a calibration, a check, an ISO 9283 test): read from its
    # ``kind`` event where an earlier cellcal stored one, an ISO 9283 test of the first
    # kind from its ``iso9283`` event, a calibration otherwise
    db.execute("ALTER TABLE campaigns ADD COLUMN kind TEXT NOT NULL DEFAULT 'calibration'")
    db.execute(
        """UPDATE campaigns SET kind = coalesce(
            (SELECT json_extract(e.message, '$.kind') FROM events e
             WHERE e.campaign_id = campaigns.id AND e.kind = 'kind'
             AND json_valid(e.message) ORDER BY e.id LIMIT 1),
            (SELECT 'iso9283' FROM events e
             WHERE e.campaign_id = campaigns.id AND e.kind = 'iso9283' LIMIT 1),
            'calibration')"""
    )
    # every calibrated model, valid from its calibration until a newer model or a failed
    # check ends it (``ended_by`` says which); the models of earlier campaigns are added
    # in their order, each ended by the next
    db.execute(
        """CREATE TABLE models (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL REFERENCES campaigns(id),
            created TEXT NOT NULL,
            valid_from TEXT NOT NULL,
            valid_until TEXT,
            ended_by TEXT,
            model_toml TEXT NOT NULL,
            digest TEXT NOT NULL
        )"""
    )
    db.execute(
        """CREATE TABLE checks (
            id INTEGER PRIMARY KEY,
            campaign_id INTEGER NOT NULL UNIQUE REFERENCES campaigns(id),
            model_id INTEGER REFERENCES models(id),
            model_digest TEXT NOT NULL,
            created TEXT NOT NULL,
            n_poses INTEGER NOT NULL,
            rms_mm REAL NOT NULL,
            max_mm REAL NOT NULL,
            warning_mm REAL NOT NULL,
            limit_mm REAL NOT NULL,
            verdict TEXT NOT NULL,
            cause TEXT,
            errors_mm TEXT NOT NULL
        )"""
    )
    rows = db.execute(
        """SELECT c.campaign_id, c.created, c.model_toml FROM calibrations c
        JOIN campaigns k ON k.id = c.campaign_id
        WHERE k.status = 'complete' AND c.id = (SELECT max(id) FROM calibrations
            WHERE campaign_id = c.campaign_id)
        ORDER BY c.id"""
    ).fetchall()
    previous = None
    for campaign_id, created, text in rows:
        if previous is not None:
            db.execute(
                "UPDATE models SET valid_until = ?, ended_by = ? WHERE id = ?",
                (created, f"model of campaign {campaign_id}", previous),
            )
        cur = db.execute(
            """INSERT INTO models (campaign_id, created, valid_from, model_toml, digest)
            VALUES (?, ?, ?, ?, ?)""",
            (campaign_id, created, created, text, model_digest(text)),
        )
        previous = cur.lastrowid


#: a campaign in one of these states is finished: it goes to the fleet whole
FINISHED = ("complete", "refused", "aborted", "failed")


def _schema_7(db: sqlite_utils.Database) -> None:
    # The fleet's outbox: what to send to the central PostgreSQL, in order. Triggers fill
    # it in the transaction that makes the change, whatever code makes it: a campaign
    # that finished (sent whole: its rows, its analysis, its check), a model made or
    # ended. The sender marks an entry sent once the server committed it.
    db.execute(
        """CREATE TABLE outbox (
            id INTEGER PRIMARY KEY AUTOINCREMENT,
            kind TEXT NOT NULL,
            ref INTEGER NOT NULL,
            created TEXT NOT NULL,
            sent TEXT
        )"""
    )
    db.execute("CREATE INDEX outbox_unsent ON outbox (id) WHERE sent IS NULL")
    finished = ", ".join(f"'{s}'" for s in FINISHED)
    now = "strftime('%Y-%m-%dT%H:%M:%fZ', 'now')"
    db.execute(
        f"""CREATE TRIGGER outbox_campaign AFTER UPDATE OF status ON campaigns
        WHEN NEW.status IN ({finished}) AND OLD.status IS NOT NEW.status
        BEGIN INSERT INTO outbox (kind, ref, created) VALUES ('campaign', NEW.id, {now}); END"""
    )
    # an event written after its campaign finished (an operator's abort, noted after the
    # status): the campaign goes again, whole (its rows are keyed: nothing twice)
    db.execute(
        f"""CREATE TRIGGER outbox_late_event AFTER INSERT ON events
        WHEN (SELECT status FROM campaigns WHERE id = NEW.campaign_id) IN ({finished})
        BEGIN INSERT INTO outbox (kind, ref, created) VALUES ('campaign', NEW.campaign_id, {now});
        END"""
    )
    db.execute(
        f"""CREATE TRIGGER outbox_model AFTER INSERT ON models
        BEGIN INSERT INTO outbox (kind, ref, created) VALUES ('model', NEW.id, {now}); END"""
    )
    db.execute(
        f"""CREATE TRIGGER outbox_model_ended AFTER UPDATE OF valid_until ON models
        BEGIN INSERT INTO outbox (kind, ref, created) VALUES ('model', NEW.id, {now}); END"""
    )
    # what is already there goes too, in the order it was made
    db.execute(
        f"""INSERT INTO outbox (kind, ref, created)
        SELECT kind, ref, created FROM (
            SELECT 'campaign' AS kind, id AS ref, coalesce(finished, created) AS created
            FROM campaigns WHERE status IN ({finished})
            UNION ALL SELECT 'model', id, created FROM models)
        ORDER BY created, kind, ref"""
    )
    # per table, the last row id sent and how many; the sender's last attempt and error
    db.execute(
        """CREATE TABLE fleet_sent (
            table_name TEXT PRIMARY KEY,
            last_id INTEGER,
            rows INTEGER NOT NULL
        )"""
    )
    db.execute("CREATE TABLE fleet_state (key TEXT PRIMARY KEY, value TEXT)")


def model_digest(text: str) -> str:
    """A model's fingerprint: the SHA-256 of its text (hex, 16 digits), which a check, a
    compensation and a report name it by."""
    return hashlib.sha256(text.encode()).hexdigest()[:16]


MIGRATIONS: tuple[Callable[[sqlite_utils.Database], None], ...] = (
    _schema_1,
    _schema_2,
    _schema_3,
    _schema_4,
    _schema_5,
    _schema_6,
    _schema_7,
)


#: The tables every campaign database has; a file without any of them is another's.
CORE_TABLES = ("campaigns", "poses", "samples")


@functools.cache
def expected_columns(version: int) -> dict[str, frozenset[str]]:
    """The tables and columns of schema ``version`` (the migrations run on a database in
    memory)."""
    conn = sqlite3.connect(":memory:")
    try:
        db = sqlite_utils.Database(conn)
        for migrate in MIGRATIONS[:version]:
            migrate(db)
        return {t: frozenset(c.name for c in db[t].columns) for t in db.table_names()}
    finally:
        conn.close()


@functools.cache
def column_types(version: int) -> dict[str, dict[str, str]]:
    """Each table's columns of schema ``version`` in order, with their declared types."""
    conn = sqlite3.connect(":memory:")
    try:
        db = sqlite_utils.Database(conn)
        for migrate in MIGRATIONS[:version]:
            migrate(db)
        return {
            t: {str(r[1]): str(r[2]) for r in conn.execute(f"PRAGMA table_info({t})")}
            for t in db.table_names()
        }
    finally:
        conn.close()


def schema_problem(tables: dict[str, set[str]], version: int) -> str | None:
    """What is wrong with a file's ``tables`` (name → columns) for the schema its
    ``user_version`` says, in words; None when they fit. A newer version is the caller's
    to refuse (it may be a newer cellcal's file)."""
    if version < 0:
        return (
            f"not a cellcal database: its user_version {version} is no schema version "
            f"(cellcal's are 1 to {SCHEMA_VERSION})"
        )
    if version == 0:
        return "not a cellcal database (an SQLite file of another program)" if tables else None
    if version > SCHEMA_VERSION:
        return None
    if not set(CORE_TABLES) & set(tables):
        return (
            f"not a cellcal database: an SQLite file of another program (schema version "
            f"{version} but no cellcal tables)"
        )
    missing = []
    for table, columns in sorted(expected_columns(version).items()):
        if table not in tables:
            missing.append(f"table {table}")
        elif lacking := sorted(columns - tables[table]):
            missing.append(f"{table}.{', '.join(lacking)}")
    if missing:
        return (
            f"not a complete cellcal database of schema {version}: no {'; no '.join(missing)} "
            "(changed by another program, or damaged?)"
        )
    fits = [
        v
        for v in range(version, SCHEMA_VERSION + 1)
        if all(c <= tables.get(t, set()) for t, c in expected_columns(v).items())
    ]
    if fits[-1] > version:
        return (
            f"its user_version says schema {version} but its tables are schema {fits[-1]}'s: "
            f"the version was changed by another program (PRAGMA user_version = {fits[-1]} "
            "puts it right)"
        )
    return None
