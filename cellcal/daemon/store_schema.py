"""The campaign database's schema: one function per version, applied in order.

The version is SQLite's ``user_version``: schema 1 holds the acquisition (``campaigns``,
``poses``, ``samples``, ``events``), schema 2 adds the analysis (``registrations``,
``calibrations``, ``reports``). :data:`MIGRATIONS` [v] brings a file from version v to
v + 1; ``cellcal.daemon.store`` runs them when it opens an older file. The core tables
and columns are public (``docs/database.md``) and are never renamed.
"""

from __future__ import annotations

from collections.abc import Callable

import sqlite_utils

SCHEMA_VERSION = 2


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


MIGRATIONS: tuple[Callable[[sqlite_utils.Database], None], ...] = (_schema_1, _schema_2)
