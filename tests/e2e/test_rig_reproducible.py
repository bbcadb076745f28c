"""A small campaign with the camera rig through its GigE Vision twins, run twice with one
seed: the same images, the same sets, the same numbers, row for row, whatever the load;
and every rig pose stored with ``samples_per_pose`` samples or an event saying why not."""

from __future__ import annotations

import os
import sqlite3

import pytest

from cellcal.campaign.runner import start_campaign
from cellcal.config import config_from_dict
from cellcal.drivers.cameras.aravis import aravis_missing
from cellcal.families import find
from cellcal.mocks import netns
from tests.drivers.families import cell_for

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(180)]

SAMPLES = 8
ROWS = """SELECT p.idx, s.sensor, s.host_time, s.device_time, s.x, s.y, s.z, s.cov_xx, s.cov_xy,
    s.cov_xz, s.cov_yy, s.cov_yz, s.cov_zz, s.ori_w, s.ori_x, s.ori_y, s.ori_z
    FROM samples s JOIN poses p ON p.id = s.pose_id ORDER BY p.idx, s.sensor, s.id"""


def _gige_or_skip() -> None:
    """The rig's twin needs Aravis and a network namespace; without them a campaign would
    simulate the cameras in-process, which is not what this test is about."""
    if reason := aravis_missing():
        pytest.skip(reason)
    try:
        _, fd = netns.run_in_new_netns([], lambda: None)
    except netns.NamespaceUnavailableError as exc:
        pytest.skip(str(exc))
    os.close(fd)


def _small_rig_cell():
    data = cell_for(find("sensor", "photogrammetry", "cameras")).model_dump()
    data["campaign"].update(
        grid=[2, 2, 3], validation_inside=2, validation_per_region=1, samples_per_pose=SAMPLES
    )
    return config_from_dict(data, "small rig cell")


def _run(config, db) -> sqlite3.Connection:
    out = start_campaign(config, str(db), config_path=None, mock=True, seed=7)
    assert out.summary is not None
    return sqlite3.connect(db)


def test_one_seed_stores_the_same_rig_rows_and_every_pose_keeps_its_samples_or_says_why(
    tmp_path, caplog
):
    _gige_or_skip()
    config = _small_rig_cell()
    with caplog.at_level("WARNING"):
        a = _run(config, tmp_path / "a.db")
        b = _run(config, tmp_path / "b.db")
    assert "simulated in-process" not in caplog.text  # the GigE Vision twins served
    rows = a.execute(ROWS).fetchall()
    assert sum(r[1] == "rig" for r in rows) >= 12 * SAMPLES
    assert rows == b.execute(ROWS).fetchall()
    events = "SELECT kind, pose_idx, message FROM events WHERE kind != 'device' ORDER BY id"
    assert a.execute(events).fetchall() == b.execute(events).fetchall()
    # every pose has the rig's samples_per_pose samples, or an event that says why not
    counts = dict(
        a.execute(
            "SELECT p.idx, (SELECT COUNT(*) FROM samples s WHERE s.pose_id = p.id "
            "AND s.sensor = 'rig') FROM poses p"
        ).fetchall()
    )
    said = {
        (kind, idx)
        for kind, idx in a.execute("SELECT kind, pose_idx FROM events WHERE pose_idx IS NOT NULL")
    }
    for idx, n in counts.items():
        if n == 0:
            assert ("no-target", idx) in said, idx
        elif n != SAMPLES:
            assert ("short-series", idx) in said and n < SAMPLES, idx
    a.close()
    b.close()
