"""D- and I-optimal poses: more information (or less prediction variance) than random
picks of the same candidates, the exchange's arithmetic, the campaign's config keys,
refusals, a calibration from 30 chosen poses about as good as the paper's 80-pose
cube on simulated robots, and poses chosen over the workspace box that predict it
better than poses chosen from the cube."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.kinematics import target_kinematics
from cellcal.calib.pose_selection import (
    _swap_values,
    d_optimal,
    i_optimal,
    information,
    mean_variance,
    nearest_neighbour_order,
    prediction_rms,
    workspace_weights,
)
from cellcal.campaign.plan import (
    CALIBRATION,
    VALIDATION,
    expected_rms,
    identification_blocks,
    make_plan,
    workspace_poses,
)
from cellcal.config import load_config
from cellcal.errors import InputError
from cellcal.files.models import load_model
from tests.conftest import TRACKER_CELL


@pytest.fixture(scope="module")
def cell():
    config = load_config(TRACKER_CELL, relative_paths=False)
    nominal = load_model(config.robot.model).model
    home = np.radians(config.robot.home_deg)
    offset = np.asarray(config.reference_sensor.target_offset_mm, dtype=float)
    return config, nominal, home, offset


def _benchmark():
    """benchmarks/pose_selection.py, whose comparison the last test runs small."""
    path = Path(__file__).parents[2] / "benchmarks" / "pose_selection.py"
    spec = importlib.util.spec_from_file_location("pose_selection_benchmark", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _logdet(M):
    return np.linalg.slogdet(M)[1]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_d_optimal_beats_random_picks_of_the_same_candidates(cell, seed):
    config, nominal, home, offset = cell
    pool = make_plan(
        config.campaign.model_copy(update={"optimal_poses": 24, "seed": seed}),
        nominal,
        home,
        offset,
        select=False,
    )
    q = np.array([p.q for p in pool.poses if p.role == CALIBRATION])
    G, _, names = identification_blocks(nominal, q, offset)
    assert len(names) == G.shape[2] == 27  # the KR 5 arc's identifiable set, frame included
    chosen = d_optimal(G, 24)
    assert len(set(chosen.chosen)) == 24
    assert chosen.log_det == pytest.approx(_logdet(information(G, list(chosen.chosen))))
    # Exchanges only ever raise the determinant, and end where the result says.
    assert np.all(np.diff(chosen.history) > -1e-6) and chosen.history[-1] == chosen.log_det
    rng = np.random.default_rng(seed)
    randoms = [_logdet(information(G, rng.choice(len(q), 24, replace=False))) for _ in range(50)]
    assert chosen.log_det > max(randoms)
    assert d_optimal(G, 24) == chosen  # deterministic


@pytest.fixture(scope="module")
def blocks(cell):
    """The bundled tracker cell's 320 candidates and its workspace points, as blocks."""
    config, nominal, home, offset = cell
    campaign = config.campaign.model_copy(update={"optimal_poses": 24})
    pool = make_plan(campaign, nominal, home, offset, select=False)
    q = np.array([p.q for p in pool.poses if p.role == CALIBRATION])
    workspace = workspace_poses(campaign, nominal, home, offset)
    G, H, _ = identification_blocks(nominal, q, offset, workspace)
    return q, workspace, G, H


def test_the_exchange_scores_every_swap_as_recomputing_would(blocks):
    _, _, G, H = blocks
    A = workspace_weights(H, G.shape[2])
    chosen = list(d_optimal(G, 24).chosen)
    M = information(G, chosen)
    M_inv = np.linalg.inv(M)
    delta = _swap_values(G, M_inv, M_inv @ A @ M_inv, chosen[5])
    for k in (0, 17, 101, 250):
        if k in chosen:
            continue
        swapped = [k if c == chosen[5] else c for c in chosen]
        direct = mean_variance(information(G, swapped), A) - mean_variance(M, A)
        assert delta[k] == pytest.approx(direct, rel=1e-6, abs=1e-9)


def test_i_optimal_poses_predict_better_than_d_optimal_and_random_ones(cell, blocks):
    _, nominal, _, offset = cell
    q, workspace, G, H = blocks
    assert G.shape == (320, 3, 27) and H.shape[1:] == (3, 27) and len(H) > 100
    d = d_optimal(G, 24)
    i = i_optimal(G, H, 24)
    assert i.criterion == "I" and len(set(i.chosen)) == 24
    # Exchanges only lower the mean variance; the D-optimal set is where they start.
    assert i.history[0] == pytest.approx(prediction_rms(G, H, d.chosen) ** 2)
    assert np.all(np.diff(i.history) < 0)
    assert i.prediction_rms == pytest.approx(prediction_rms(G, H, i.chosen))
    assert i.prediction_rms < 0.9 * prediction_rms(G, H, d.chosen)
    rng = np.random.default_rng(4)
    randoms = [prediction_rms(G, H, rng.choice(len(G), 24, replace=False)) for _ in range(50)]
    assert i.prediction_rms < min(randoms)
    # The plan's figure is the same number, from the joints.
    assert expected_rms(nominal, q[list(i.chosen)], offset, workspace) == pytest.approx(
        i.prediction_rms
    )
    assert i_optimal(G, H, 24) == i  # deterministic
    with pytest.raises(InputError, match="workspace points"):
        i_optimal(G, H[:, :, :5], 24)


def test_too_few_or_too_many_poses_are_refused(cell):
    config, nominal, home, offset = cell
    rng = np.random.default_rng(3)
    G = rng.normal(size=(40, 3, 27))
    # 3N equations must outnumber the 27 parameters, as the campaign itself demands.
    with pytest.raises(InputError, match="at least 10"):
        d_optimal(G, 9)
    assert len(d_optimal(G, 10).chosen) == 10
    with pytest.raises(InputError, match="40 reachable candidates"):
        d_optimal(G, 41)
    with pytest.raises(InputError, match="finite"):
        d_optimal(np.full((40, 3, 27), np.nan), 12)
    with pytest.raises(InputError, match="at least 10"):
        make_plan(config.campaign.model_copy(update={"optimal_poses": 5}), nominal, home, offset)


def test_the_campaign_key_picks_n_poses_in_a_short_tour(cell):
    config, nominal, home, offset = cell
    full = make_plan(config.campaign, nominal, home, offset)
    plan = make_plan(
        config.campaign.model_copy(update={"optimal_poses": 20}), nominal, home, offset
    )
    assert plan.count(CALIBRATION) == 20 and plan.selection is not None
    assert plan.candidates == 320
    # The validation poses are the full plan's, and every pose is in the box and limits.
    val = [p for p in plan.poses if p.role == VALIDATION]
    np.testing.assert_allclose(
        [p.q for p in val], [p.q for p in full.poses if p.role == VALIDATION]
    )
    assert [p.idx for p in plan.poses] == list(range(len(plan.poses)))
    lo, hi = nominal.limits
    assert all(((p.q >= lo) & (p.q <= hi)).all() for p in plan.poses)
    box_lo, box_hi = np.array(config.campaign.workspace_min_mm), config.campaign.workspace_max_mm
    assert all(((p.target_mm >= box_lo) & (p.target_mm <= box_hi)).all() for p in plan.poses)
    # The chosen poses are where the nominal model puts the target: reachable as planned.
    q_all = np.array([p.q for p in plan.poses])
    reached = target_kinematics(nominal, q_all, offset, jacobian=False).p
    np.testing.assert_allclose(reached, [p.target_mm for p in plan.poses], atol=1e-3)
    # The same configuration gives the same plan (a resumed campaign checks its digest).
    again = make_plan(
        config.campaign.model_copy(update={"optimal_poses": 20}), nominal, home, offset
    )
    assert again.digest == plan.digest
    by_i = make_plan(
        config.campaign.model_copy(update={"optimal_poses": 20, "optimal_criterion": "I"}),
        nominal,
        home,
        offset,
    )
    assert by_i.selection is not None and by_i.selection.criterion == "I"
    assert by_i.count(CALIBRATION) == 20 and by_i.digest != plan.digest
    assert plan.selection.prediction_rms > by_i.selection.prediction_rms
    q = np.array([p.q for p in plan.poses if p.role == CALIBRATION])
    tour = np.abs(np.diff(np.vstack([home, q]), axis=0)).max(axis=1).sum()
    rng = np.random.default_rng(1)
    shuffled = np.vstack([home, q[rng.permutation(len(q))]])
    assert tour < np.abs(np.diff(shuffled, axis=0)).max(axis=1).sum()
    assert nearest_neighbour_order(q, home)[0] == int(np.argmin(np.abs(q - home).max(axis=1)))


def test_30_chosen_poses_calibrate_about_as_well_as_the_80_pose_cube():
    # The median over ten simulated robots: one robot's held-out error varies by 2× with
    # its noise draw, so fewer robots would test luck.
    (row,) = _benchmark().held_out("kuka-kr5-arc", (30,), tuple(range(31, 41)))
    print(
        f"held-out RMS: 30 D-optimal {row.optimal_mm:.4f} mm, 30 I-optimal "
        f"{row.i_optimal_mm:.4f} mm, 30 random {row.random_mm:.4f} mm, "
        f"80-pose cube {row.cube_mm:.4f} mm"
    )
    assert row.optimal_mm < 1.5 * row.cube_mm
    assert row.i_optimal_mm < 1.1 * row.cube_mm
    assert max(row.optimal_mm, row.i_optimal_mm) < row.random_mm
    assert max(row.minutes, row.i_minutes) < 0.8 * row.cube_minutes


@pytest.mark.slow
def test_poses_chosen_over_the_workspace_predict_it_better_than_the_cubes():
    # Judged at reachable poses drawn over the bundled cell's workspace box (held out:
    # another seed than the plan's candidates and workspace points), median of five
    # simulated robots: where the cube's candidates leave the arm's far reaches to
    # extrapolation, candidates drawn over the box cover them.
    (row,) = _benchmark().over_workspace("kuka-kr5-arc", (30,), (31, 32, 33, 34, 35), ("D",), 150)
    print(
        f"held-out RMS over the box: 30 D-optimal of the box {row.workspace_mm:.4f} mm, of "
        f"the cube {row.cube_optimal_mm:.4f} mm, 30 random over the box {row.random_mm:.4f} "
        f"mm, 80-pose cube {row.cube_mm:.4f} mm"
    )
    assert row.held_out == 150
    assert row.workspace_mm < 0.5 * row.cube_optimal_mm
    assert row.workspace_mm < row.random_mm and row.workspace_mm < 0.5 * row.cube_mm
    # The plan expects it too (its own workspace points, not the held-out ones).
    assert row.expected_mm[0] < 0.5 * row.expected_mm[1]
    # And the poses spread over the box predict the cube and O1–O5 no worse either.
    assert row.at_validation_mm[0] < row.at_validation_mm[1]


@pytest.mark.twin
@pytest.mark.slow
@pytest.mark.parametrize("region", ["cube", "workspace"])
def test_a_campaign_with_chosen_poses_runs_and_finds_its_plan_again(cell, tmp_path, region):
    from cellcal.campaign.runner import start_campaign, stored_campaign
    from cellcal.store.database import Store

    config, _, _, _ = cell
    update = {"optimal_poses": 16, "region": region}
    config = config.model_copy(update={"campaign": config.campaign.model_copy(update=update)})
    db = str(tmp_path / "c.db")
    out = start_campaign(config, db, config_path=None, mock=True)
    assert out.plan.count(CALIBRATION) == 16 and out.summary is not None
    assert out.summary.n_calibration == 16
    assert {p.region for p in out.plan.poses if p.role == CALIBRATION} == {region}
    store = Store(db, readonly=True)
    try:
        again = stored_campaign(store, out.campaign_id).plan
    finally:
        store.close()
    assert again.digest == out.plan.digest  # what --resume checks
