"""The models a cell carried and the checks of them (schema 6): a new model ends the
previous one, a failed check ends its model, a file of schema 5 gets its models from
its calibrations and its campaigns' kinds from their events, a read-only older file has
none; the check kind's options are refused in one line and completed from the database."""

from __future__ import annotations

import json
import sqlite3

import pytest
import sqlite_utils

from cellcal.campaign.check_kind import CHECK_KIND
from cellcal.errors import InputError
from cellcal.store.database import MIGRATIONS, SCHEMA_VERSION, Store
from cellcal.store.schema import model_digest
from tests.daemon.test_store import _campaign


def test_a_new_model_ends_the_previous_one_and_a_failed_check_ends_its_own(tmp_path):
    store = Store(tmp_path / "c.db")
    a, b, c = (_campaign(store) for _ in range(3))
    first = store.add_model(a, "model A\n")
    assert store.current_model().id == first
    second = store.add_model(b, "model B\n")
    old, new = store.models()
    assert (old.id, new.id) == (first, second) and new.current and not old.current
    assert old.valid_until == new.valid_from and old.ended_by == f"model {second} (campaign {b})"
    assert new.digest == model_digest("model B\n") and store.model_of_campaign(b) == new

    common = {"rms_mm": 0.1, "max_mm": 0.2, "warning_mm": 0.02, "limit_mm": 0.03}
    store.add_check(c, second, new.digest, verdict="recalibrate", cause="joint 2 offset",
                    errors_mm=(0.1, 0.2), ends_model=True, **common)  # fmt: skip
    assert store.current_model() is None
    ended = store.model(second)
    assert ended.ended_by == f"check campaign {c} (recalibrate)"
    (check,) = store.checks(second)
    assert (check.verdict, check.cause, check.errors_mm, check.n_poses) == (
        "recalibrate", "joint 2 offset", (0.1, 0.2), 2,
    )  # fmt: skip
    assert store.check_of_campaign(c) == check
    store.end_model(first, "again")  # an ended model keeps its end
    assert store.model(first).ended_by == old.ended_by
    store.close()


def _schema_5_file(path):
    conn = sqlite3.connect(path, isolation_level=None)
    db = sqlite_utils.Database(conn)
    for migrate in MIGRATIONS[:5]:
        migrate(db)
    conn.execute("PRAGMA user_version = 5")
    for cid, status in ((1, "complete"), (2, "complete"), (3, "complete"), (4, "refused")):
        conn.execute(
            """INSERT INTO campaigns (id, created, status, mock, seed, time_scale, model,
            sensors, n_poses, samples_per_pose, dwell_s, plan_digest, config_json)
            VALUES (?, '2026-01-01', ?, 1, 1, 0, 'ur10e', '["tracker"]', 1, 2, 7, 'x', '{}')""",
            (cid, status),
        )
    conn.execute(
        """INSERT INTO events (campaign_id, time, kind, message) VALUES
        (2, 't', 'kind', ?), (3, 't', 'iso9283', '5 cycles')""",
        (json.dumps({"kind": "iso9283", "options": {}}),),
    )
    for cid, text in ((1, "first"), (4, "refused one"), (1, "first, analysed again")):
        conn.execute(
            """INSERT INTO calibrations (campaign_id, sensor, created, n_points, rms_before_mm,
            rms_after_mm, condition_number, identified, unidentifiable, model_toml)
            VALUES (?, 'tracker', ?, 1, 1, 1, 1, '[]', '[]', ?)""",
            (cid, f"2026-01-0{cid}", text),
        )
    conn.close()


def test_a_schema_5_file_gets_its_models_and_kinds(tmp_path):
    path = tmp_path / "old.db"
    _schema_5_file(path)
    reader = Store(path, readonly=True)  # read as it is: no models yet, nothing written
    assert reader.models() == [] and reader.current_model() is None and reader.checks() == []
    reader.close()
    store = Store(path)
    assert store.schema_version == SCHEMA_VERSION
    (model,) = store.models()  # the complete calibration's last model; not the refused one
    assert (model.campaign_id, model.model_toml, model.current) == (
        1, "first, analysed again", True,
    )  # fmt: skip
    rows = dict(store.conn.execute("SELECT id, kind FROM campaigns").fetchall())
    assert rows == {1: "calibration", 2: "iso9283", 3: "iso9283", 4: "calibration"}
    store.close()


def test_the_check_kinds_options_are_refused_in_one_line(tmp_path):
    for raw, words in (
        ({"cycles": 3}, "a check takes no option 'cycles'"),
        ({"poses": 3}, "poses 3: a whole number from 6 to 200"),
        ({"poses": 12}, "a check needs the model it compares with"),
        ({"model_toml": "[x]\n", "model": "m"}, "m: "),
        ({"model_toml": "x = 1\n", "model": "m", "model_id": "1"}, "model_id must be"),
    ):
        with pytest.raises(InputError) as refused:
            CHECK_KIND.options(raw)
        assert words in str(refused.value) and "\n" not in str(refused.value)


def test_the_check_takes_the_databases_current_model_or_names_why_there_is_none(tmp_path):
    with pytest.raises(InputError, match="no current model in the database: no calibration"):
        CHECK_KIND.from_database({}, None)
    store = Store(tmp_path / "c.db")
    cid = _campaign(store)
    with pytest.raises(InputError, match="no calibration is stored in it"):
        CHECK_KIND.from_database({"poses": 8}, store)
    mid = store.add_model(cid, "the model\n")
    got = CHECK_KIND.from_database({"poses": 8}, store)
    assert got == {
        "poses": 8, "model": f"model {mid} (campaign {cid})", "model_toml": "the model\n",
        "model_id": mid,
    }  # fmt: skip
    # a file of the same text is that model; another text is none of the database's
    same = CHECK_KIND.from_database({"model": "f.toml", "model_toml": "the model\n"}, store)
    other = CHECK_KIND.from_database({"model": "g.toml", "model_toml": "another\n"}, store)
    assert (same["model_id"], other["model_id"]) == (mid, None)
    store.end_model(mid, "check campaign 9 (recalibrate)")
    with pytest.raises(InputError, match=f"model {mid} was ended by check campaign 9"):
        CHECK_KIND.from_database({}, store)
    store.close()
