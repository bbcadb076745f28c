"""The campaign database: round trip, atomic poses, migration, refusal of strange files."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest
import sqlite_utils

from cellcal import __version__
from cellcal.drivers.base import Series
from cellcal.errors import CampaignError
from cellcal.store.database import MIGRATIONS, SCHEMA_VERSION, Store, StoreError


def _campaign(store, n_poses=3):
    return store.create_campaign(
        config_json="{}",
        config_path=None,
        mock=True,
        seed=1,
        time_scale=0.0,
        model="kuka-kr5-arc",
        sensors=["tracker", "rig"],
        n_poses=n_poses,
        samples_per_pose=4,
        dwell_s=7.0,
        plan_digest="abc",
    )


def _series(name, n=4, offset=0.0):
    xyz = np.arange(n * 3, dtype=float).reshape(n, 3) + offset
    t = np.arange(n) * 0.1
    return Series(name, t, t + 1000.0, xyz)


def _pose(store, cid, idx, series):
    return store.add_pose(
        cid,
        idx=idx,
        role="calibration",
        region="cube",
        target_mm=np.array([1.0, 2.0, 3.0]),
        planned_q=np.radians([0, 10, 20, 30, 40, 50.0]),
        reached_q=np.radians([0, 10, 20, 30, 40, 50.0]) + 1e-6,
        t_start=0.0,
        t_end=9.0,
        series=series,
    )


def test_round_trip(tmp_path):
    store = Store(tmp_path / "c.db")
    assert store.schema_version == SCHEMA_VERSION
    cid = _campaign(store)
    _pose(store, cid, 0, [_series("tracker"), _series("rig", offset=5.0)])
    _pose(store, cid, 1, [_series("tracker", offset=1.0), _series("rig")])
    assert store.completed_indices(cid) == {0, 1}
    data = store.pose_data(cid)
    np.testing.assert_allclose(data.mean["tracker"][1], _series("tracker", offset=1.0).mean)
    np.testing.assert_allclose(data.std["rig"][0], _series("rig").std)
    np.testing.assert_allclose(data.q[0], np.radians([0, 10, 20, 30, 40, 50.0]) + 1e-6, atol=1e-9)
    assert data.role == ("calibration", "calibration")
    store.close()
    # Other tools read the core directly.
    db = sqlite_utils.Database(tmp_path / "c.db")
    assert db["samples"].count == 16
    assert {"campaigns", "poses", "samples"} <= set(db.table_names())
    row = next(
        db.query("SELECT sensor, host_time, device_time, x FROM samples ORDER BY id LIMIT 1")
    )
    assert row == {"sensor": "tracker", "host_time": 0.0, "device_time": 1000.0, "x": 0.0}


def test_a_pose_is_stored_once_and_wholly(tmp_path):
    store = Store(tmp_path / "c.db")
    cid = _campaign(store)
    _pose(store, cid, 0, [_series("tracker")])
    with pytest.raises(CampaignError, match="already stored"):
        _pose(store, cid, 0, [_series("tracker")])

    class Broken(Series):
        @property
        def mean(self):
            raise RuntimeError("sensor died while its samples were being stored")

    with pytest.raises(RuntimeError):
        _pose(
            store,
            cid,
            1,
            [_series("tracker"), Broken("rig", np.zeros(2), np.zeros(2), np.zeros((2, 3)))],
        )
    # Nothing of pose 1 remains: no pose row, no samples, no statistics.
    assert store.completed_indices(cid) == {0}
    assert store.conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0] == 4
    assert store.conn.execute("SELECT COUNT(*) FROM pose_stats").fetchone()[0] == 1


def test_migration_from_schema_1_keeps_the_data(tmp_path):
    path = tmp_path / "old.db"
    conn = sqlite3.connect(path, isolation_level=None)
    db = sqlite_utils.Database(conn)
    MIGRATIONS[0](db)
    conn.execute("PRAGMA user_version = 1")
    conn.execute(
        """INSERT INTO campaigns (created, status, mock, seed, time_scale, model, sensors, n_poses,
        samples_per_pose, dwell_s, plan_digest, config_path, config_json)
        VALUES ('2026-01-01', 'complete', 1, 1, 0, 'ur10e', '["tracker"]', 5, 20, 7, 'x',
        NULL, '{}')"""
    )
    conn.close()
    store = Store(path)
    assert store.schema_version == SCHEMA_VERSION
    assert store.campaign(1).model == "ur10e"
    assert {"registrations", "calibrations", "reports", "fused"} <= set(store.db.table_names())
    store.add_report(1, {"ok": True})
    assert store.latest_report(1) == {"ok": True}


def _schema_2_file(path):
    """A campaign database as cellcal wrote it before per-sample covariances."""
    conn = sqlite3.connect(path, isolation_level=None)
    db = sqlite_utils.Database(conn)
    MIGRATIONS[0](db)
    MIGRATIONS[1](db)
    conn.execute("PRAGMA user_version = 2")
    conn.execute(
        """INSERT INTO campaigns (created, status, mock, seed, time_scale, model, sensors, n_poses,
        samples_per_pose, dwell_s, plan_digest, config_path, config_json)
        VALUES ('2026-01-01', 'complete', 1, 1, 0, 'ur10e', '["tracker"]', 1, 2, 7, 'x',
        NULL, '{}')"""
    )
    conn.execute(
        """INSERT INTO poses (campaign_id, idx, role, region, planned_q_deg, reached_q_deg,
        t_start, t_end, stored) VALUES (1, 0, 'calibration', 'cube', '[0,0,0,0,0,0]',
        '[0,0,0,0,0,0]', 0, 1, 'x')"""
    )
    conn.execute(
        """INSERT INTO samples (pose_id, sensor, host_time, device_time, x, y, z)
        VALUES (1, 'tracker', 0, 0, 1, 2, 3), (1, 'tracker', 0.1, 0.1, 1, 2, 5)"""
    )
    conn.execute(
        """INSERT INTO pose_stats (pose_id, sensor, n, mean_x, mean_y, mean_z, std_x, std_y,
        std_z, retries) VALUES (1, 'tracker', 2, 1, 2, 4, 0, 0, 1.4142, 0)"""
    )
    conn.close()


def test_a_schema_2_file_reads_read_only_and_migrates_keeping_its_samples(tmp_path):
    path = tmp_path / "v2.db"
    _schema_2_file(path)
    old = Store(path, readonly=True)
    assert old.schema_version == 2
    data = old.pose_data(1)
    np.testing.assert_allclose(data.mean["tracker"][0], [1, 2, 4])
    assert np.isnan(data.cov["tracker"][0]).all()
    assert old.acquired_with(1) is None  # read as it is: no version column to read
    old.close()
    store = Store(path)
    assert store.schema_version == SCHEMA_VERSION
    data = store.pose_data(1)
    np.testing.assert_allclose(data.mean["tracker"][0], [1, 2, 4])
    assert data.measured("tracker").tolist() == [True]
    assert data.measured("rig").tolist() == [False]
    rows = store.conn.execute("SELECT z, cov_xx, ori_w FROM samples ORDER BY id").fetchall()
    assert rows == [(3.0, None, None), (5.0, None, None)]
    # an old campaign says it does not know which cellcal acquired it; a new one does
    assert store.conn.execute("SELECT cellcal_version FROM campaigns").fetchall() == [(None,)]
    assert store.acquired_with(1) is None
    cid = _campaign(store)
    version = store.conn.execute("SELECT cellcal_version FROM campaigns WHERE id = ?", (cid,))
    assert version.fetchone() == (__version__,) and store.acquired_with(cid) == __version__


def test_covariances_and_orientations_round_trip(tmp_path):
    store = Store(tmp_path / "c.db")
    cid = _campaign(store)
    n = 3
    rng = np.random.default_rng(4)
    a = rng.normal(size=(n, 3, 3))
    cov = a @ a.transpose(0, 2, 1) * 1e-4
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = np.arange(n) * 0.1
    rig = Series("rig", t, t, rng.normal(size=(n, 3)), cov=cov, orientation=q)
    _pose(store, cid, 0, [_series("tracker"), rig])
    data = store.pose_data(cid)
    # the mean's covariance: the samples' averaged over n (the sensor gave no other)
    np.testing.assert_allclose(data.cov["rig"][0], cov.mean(axis=0) / n, rtol=1e-12)
    assert np.isnan(data.cov["tracker"][0]).all()
    stored = store.conn.execute(
        "SELECT cov_xx, cov_xy, cov_zz, ori_w, ori_z FROM samples WHERE sensor = 'rig' ORDER BY id"
    ).fetchall()
    np.testing.assert_allclose(
        stored, np.column_stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 2, 2], q[:, 0], q[:, 3]])
    )
    # a sensor's own covariance of the mean (a floor that does not average) wins
    floor = np.eye(3) * 0.25
    own = Series("rig", t, t, rng.normal(size=(n, 3)), cov=cov, mean_cov=floor)
    _pose(store, cid, 1, [own])
    np.testing.assert_allclose(store.pose_data(cid).cov["rig"][1], floor)
    with pytest.raises(ValueError, match="covariance per sample"):
        Series("rig", t, t, np.zeros((n, 3)), cov=np.zeros((n, 3)))


def test_refuses_newer_and_foreign_files(tmp_path):
    newer = tmp_path / "newer.db"
    conn = sqlite3.connect(newer)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    conn.close()
    with pytest.raises(StoreError, match="newer"):
        Store(newer)
    foreign = tmp_path / "foreign.db"
    conn = sqlite3.connect(foreign)
    conn.execute("CREATE TABLE birds (name TEXT)")
    conn.commit()
    conn.close()
    with pytest.raises(StoreError, match="not a cellcal database"):
        Store(foreign)
    text = tmp_path / "notes.db"
    text.write_text("this is not a database, it is a shopping list\n" * 20)
    with pytest.raises(StoreError, match="not a cellcal database"):
        Store(text)
    with pytest.raises(CampaignError, match="no campaign 9"):
        Store(tmp_path / "fresh.db").campaign(9)


def test_the_air_of_each_sample_round_trip_and_an_older_file(tmp_path):
    """Schema 5: a tracker's air per sample (emScon meteo) is stored and read as ranges;
    a sensor that does not report it leaves NULL; a file older than schema 5 read-only
    has none."""
    store = Store(tmp_path / "c.db")
    cid = _campaign(store)
    air = np.array([[20.1, 1013.0, 44.0], [20.4, 1012.5, 46.5], [19.9, 1013.4, 45.0]])
    tracker = Series("tracker", np.zeros(3), np.zeros(3), np.ones((3, 3)), meteo=air)
    _pose(store, cid, 0, [tracker, _series("rig")])
    (got,) = store.air_ranges(cid)
    assert (got.sensor, got.n) == ("tracker", 3)
    assert got.low == (19.9, 1012.5, 44.0) and got.high == (20.4, 1013.4, 46.5)
    rows = store.conn.execute(
        "SELECT sensor, COUNT(temperature_c), COUNT(*) FROM samples GROUP BY sensor"
    ).fetchall()
    assert sorted(rows) == [("rig", 0, 4), ("tracker", 3, 3)]
    with pytest.raises(ValueError, match="one temperature, pressure and humidity per sample"):
        Series("tracker", np.zeros(3), np.zeros(3), np.ones((3, 3)), meteo=air[:2])
    store.close()
    path = tmp_path / "v2.db"
    _schema_2_file(path)
    old = Store(path, readonly=True)
    assert old.air_ranges(1) == ()
    old.close()
