"""Size before work (issue 29, item 7): RANSAC on a million rows runs in bounded memory,
and a plan whose grid, validation regions or optimal selection would take hours is
refused at once with one line naming the bound."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.pose_selection import d_optimal
from cellcal.errors import InputError
from tests.conftest import TRACKER_CELL
from tests.inprocess import cellcal

RANSAC_MILLION = textwrap.dedent(
    """
    import numpy as np
    from cellcal.calib.registration import fit_rigid
    rng = np.random.default_rng(0)
    P = rng.uniform(-1000, 1000, (1_000_000, 3))
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Q = P @ R.T + [100.0, 200.0, 300.0] + rng.normal(0, 0.01, P.shape)
    Q[::10] += 50.0  # a tenth of the rows are outliers
    fit = fit_rigid(P, Q, robust="ransac", seed=1)
    assert np.abs(fit.R - R).max() < 1e-4, fit.R
    assert abs(fit.inliers.mean() - 0.9) < 0.01, fit.inliers.mean()
    print("ok")
    """
)


def _limited() -> None:
    """2 GiB of address space: the million rows take 100 MB; 44.7 GiB would not fit."""
    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ransac_on_a_million_rows_fits_in_bounded_memory():
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    run = subprocess.run(
        [sys.executable, "-c", RANSAC_MILLION],
        capture_output=True,
        text=True,
        timeout=280,
        preexec_fn=_limited,
        env=env,
    )
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-3000:]


def _cell(tmp_path: Path, **campaign: str) -> Path:
    """The tracker cell with [campaign] keys replaced (TOML values as text)."""
    lines = []
    for line in TRACKER_CELL.read_text().splitlines():
        key = line.split("=")[0].strip()
        if key in campaign:
            line = f"{key} = {campaign.pop(key)}"
        lines.append(line)
    text = "\n".join(lines) + "\n"
    if campaign:
        text = text.replace(
            "[campaign]\n", "[campaign]\n" + "".join(f"{k} = {v}\n" for k, v in campaign.items())
        )
    out = tmp_path / "cell.toml"
    out.write_text(text)
    return out


def _refusal(run) -> str:
    """The one error line, after the plan's progress lines (``planning: …``)."""
    *said, last = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr
    assert all(line.startswith("planning: ") or line.endswith("twins…") for line in said)
    assert last.startswith("cellcal: error: ")
    return last


@pytest.mark.timeout(60)
def test_a_huge_grid_with_many_optimal_poses_is_refused_at_once(tmp_path):
    cell = _cell(tmp_path, grid="[50, 50, 50]")
    line = _refusal(cellcal("plan", "--config", cell, "--optimal", "10000"))
    assert "campaign.grid 50×50×50 is 125000 points: at most 2000" in line, line
    line = _refusal(cellcal("plan", "--config", cell))
    assert "at most 2000" in line, line


@pytest.mark.timeout(60)
def test_too_many_optimal_poses_for_the_candidates_is_refused_at_once(tmp_path):
    cell = _cell(tmp_path, grid="[10, 10, 20]")  # 2000 points, 8000 candidates
    line = _refusal(cellcal("plan", "--config", cell, "--optimal", "5000"))
    assert "--optimal" in line and "8000 candidates: at most 250" in line, line


@pytest.mark.timeout(60)
def test_too_many_validation_poses_are_refused_at_once(tmp_path):
    regions = "[" + ", ".join(["[700.0, 0.0, 900.0]"] * 400) + "]"
    cell = _cell(tmp_path, validation_regions_mm=regions)
    line = _refusal(cellcal("plan", "--config", cell))
    assert "400 regions: at most 50" in line, line
    cell = _cell(tmp_path, validation_inside="10000", validation_per_region="10000")
    line = _refusal(cellcal("run", "--mock", "--config", cell, "--db", tmp_path / "c.db"))
    assert "poses to solve" in line and "at most 20000" in line, line


def test_the_selection_itself_is_bounded():
    G = np.zeros((100_000, 3, 30))
    with pytest.raises(InputError, match="at most 20 from that many"):
        d_optimal(G, 50)
