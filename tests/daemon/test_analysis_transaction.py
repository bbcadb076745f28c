"""An analysis's results — registrations, calibration, fused positions, report — are
stored in one transaction: a failure at any of them leaves none of them, and the store
stays usable for the next try."""

from __future__ import annotations

import dataclasses
import sqlite3

import numpy as np
import pytest

from cellcal.calib.kinematics import target_kinematics
from cellcal.campaign.analysis import analyse, analysis_of
from cellcal.drivers.base import Series
from cellcal.files.models import load_model
from cellcal.store.database import Store

#: the analysis's tables (the test counts their rows itself)
TABLES = ("registrations", "calibrations", "fused", "reports")
N_CAL, N_VAL = 40, 10


def _counts(store: Store) -> dict[str, int]:
    return {t: store.conn.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0] for t in TABLES}


@pytest.fixture
def campaign(tmp_path):
    """A stored campaign of one tracker that sees the nominal robot's target exactly
    (but for 5 µm of noise): the store, the campaign's id and the nominal model."""
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(1)
    lo, hi = nominal.limits
    q = rng.uniform(lo * 0.5, hi * 0.5, (N_CAL + N_VAL, nominal.dof))
    p = target_kinematics(nominal, q, np.array([10.0, 20.0, 150.0]), jacobian=False).p
    store = Store(tmp_path / "c.db")
    cid = store.create_campaign(
        config_json="{}",
        config_path=None,
        mock=True,
        seed=1,
        time_scale=0.0,
        model="kuka-kr5-arc",
        sensors=["tracker"],
        n_poses=len(q),
        samples_per_pose=4,
        dwell_s=1.0,
        plan_digest="abc",
    )
    t = np.arange(4) * 0.1
    for k in range(len(q)):
        store.add_pose(
            cid,
            idx=k,
            role="calibration" if k < N_CAL else "validation",
            region="cube",
            target_mm=p[k],
            planned_q=q[k],
            reached_q=q[k],
            t_start=float(k),
            t_end=k + 0.5,
            series=[Series("tracker", t, t + 1000.0, p[k] + rng.normal(0, 0.005, (4, 3)))],
        )
    yield store, cid, nominal
    store.close()


def test_an_analysis_is_stored_whole(campaign):
    store, cid, nominal = campaign
    summary = analyse(store, cid, nominal, "tracker", accept=True)
    assert _counts(store) == {
        "registrations": 2,  # nominal and calibrated geometry
        "calibrations": 1,
        "fused": N_CAL + N_VAL,
        "reports": 1,
    }
    report = store.latest_report(cid)
    assert report is not None and report["rms_after_mm"] == summary.validation_after.rms
    assert store.latest_model_toml(cid) is not None


@pytest.mark.parametrize(
    ("write", "after"),
    [("_insert_registration", 1), ("_insert_calibration", 0), ("_insert_fused", 20)],
)
def test_a_failure_midway_leaves_nothing(campaign, monkeypatch, write, after):
    """The ``after``+1-th call of one write fails: what was written before it in the
    analysis is gone too; the next analysis stores the whole."""
    store, cid, nominal = campaign
    real = getattr(Store, write)
    calls = []

    def failing(self, *args):
        calls.append(args)
        if len(calls) > after:
            raise OSError("the disk went away")
        real(self, *args)

    monkeypatch.setattr(Store, write, failing)
    with pytest.raises(OSError, match="the disk went away"):
        analyse(store, cid, nominal, "tracker", accept=True)
    assert len(calls) == after + 1
    assert _counts(store) == dict.fromkeys(TABLES, 0)
    assert not store.conn.in_transaction
    monkeypatch.undo()
    analyse(store, cid, nominal, "tracker", accept=True)
    assert _counts(store)["reports"] == 1 and _counts(store)["fused"] == N_CAL + N_VAL


def test_a_failure_at_the_report_leaves_nothing(campaign, monkeypatch):
    store, cid, nominal = campaign

    def failing(self, *args):
        raise RuntimeError("the last write fails")

    monkeypatch.setattr(Store, "_insert_report", failing)
    with pytest.raises(RuntimeError):
        analyse(store, cid, nominal, "tracker", accept=True)
    assert _counts(store) == dict.fromkeys(TABLES, 0)


def test_a_database_refusal_midway_rolls_back(campaign):
    """SQLite's own refusal (a fused position of a pose that does not exist: the foreign
    key) after the registrations and the calibration were written undoes them."""
    store, cid, nominal = campaign
    before = store.conn.total_changes
    _, results = analysis_of(store.pose_data(cid), cid, nominal, "tracker", accept=True)
    assert store.conn.total_changes == before  # the analysis itself writes nothing
    fused = list(results.fused)
    fused[5] = dataclasses.replace(fused[5], pose_id=10**6)
    with pytest.raises(sqlite3.IntegrityError):
        store.save_analysis(dataclasses.replace(results, fused=tuple(fused)))
    assert _counts(store) == dict.fromkeys(TABLES, 0)
    store.save_analysis(results)
    assert _counts(store)["fused"] == N_CAL + N_VAL
