"""A small copy of the bundled cell, tracker and camera rig (GigE Vision twins in a child
process), written into a folder for a campaign process to run; and the skip for
machines where the rig's twins cannot run."""

from __future__ import annotations

import os
import shutil
import sqlite3
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w

from cellcal.drivers.cameras.aravis import aravis_missing
from cellcal.mocks import netns

CONFIG = Path(__file__).resolve().parents[2] / "config"


def gige_or_skip() -> None:
    """The rig's twins need Aravis and a network namespace; without them a campaign
    would simulate the cameras in-process, with no child process to signal."""
    if reason := aravis_missing():
        pytest.skip(reason)
    try:
        _, fd = netns.run_in_new_netns([], lambda: None)
    except netns.NamespaceUnavailableError as exc:
        pytest.skip(str(exc))
    os.close(fd)


def small_rig_cell(folder: Path) -> Path:
    """The bundled cell with 19 poses of 8 samples, in ``folder`` with its rig and target
    files; the configuration's path."""
    data: dict[str, Any] = tomllib.loads((CONFIG / "mock-cell.toml").read_text())
    data["campaign"].update(
        grid=[2, 2, 3], validation_inside=2, validation_per_region=1, samples_per_pose=8
    )
    for name in ("mock-rig.toml", "mock-target.toml"):
        shutil.copy(CONFIG / name, folder / name)
    path = folder / "small-rig-cell.toml"
    path.write_text(tomli_w.dumps(data))
    return path


def count(db: Path, sql: str) -> int:
    """One number out of the database (0 while it does not exist yet)."""
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            row = conn.execute(sql).fetchone()
            return int(row[0]) if row and row[0] is not None else 0
        finally:
            conn.close()
    except sqlite3.OperationalError:
        return 0


def kinds(db: Path, campaign_id: int = 1) -> list[str]:
    conn = sqlite3.connect(db)
    try:
        rows = conn.execute(
            "SELECT kind FROM events WHERE campaign_id = ? ORDER BY id", (campaign_id,)
        ).fetchall()
    finally:
        conn.close()
    return [k for (k,) in rows]


#: What a fault would have left, and an interrupt must not.
FAULT_KINDS = {"device-error", "error", "sensor-retry"}
