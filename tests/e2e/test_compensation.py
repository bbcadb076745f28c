"""Compensated targets, measured: a mock campaign calibrates the simulated robot (which
carries the true errors); ``cellcal compensate`` turns intended points into joints; the
real drivers move the robot twin there and the tracker twin measures where the target
went. The error at those points drops from the nominal model's level to about the
campaign's validation error."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.compensation import compensate
from cellcal.calib.geometry import apply, invert
from cellcal.calib.kinematics import flange_transforms, target_kinematics
from cellcal.calib.registration import fit_rigid
from cellcal.campaign.devices import build_devices
from cellcal.campaign.plan import CALIBRATION
from cellcal.clock import SimulatedClock
from cellcal.files.models import load_model
from cellcal.store.database import Store
from tests.e2e.calibrated import calibrated_campaign, cli

pytestmark = [pytest.mark.twin, pytest.mark.timeout(300)]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """One mock campaign, its report folder (model.toml) and its validation RMS."""
    folder = tmp_path_factory.mktemp("compensate")
    config, db, outcome, _ = calibrated_campaign(folder)
    store = Store(db, readonly=True)
    try:
        data = store.pose_data(outcome.campaign_id)
    finally:
        store.close()
    return config, folder, data, outcome.summary.validation_after.rms


def _compensate(folder: Path, targets: Path, out: Path, *extra: str):
    """``cellcal compensate`` with the campaign's calibrated model."""
    model = str(folder / "report" / "model.toml")
    return cli("compensate", "--model", model, "--targets", str(targets), "--out", str(out), *extra)


def _measure(config, joints: np.ndarray) -> np.ndarray:
    """Move the robot twin to each row of joints (rad) through the real driver and
    measure the target with the tracker twin: the means (mm, tracker frame)."""
    nominal = load_model(config.robot.model).model
    devices = build_devices(
        config, nominal, SimulatedClock(), mock=True, seed=config.simulation.seed
    )
    try:
        (setting,) = devices.sensors
        out = []
        for q in joints:
            devices.robot.move_joints(q, 0.5)
            out.append(setting.sensor.measure(20, setting.rate_hz).mean)
        return np.array(out)
    finally:
        devices.close()


def test_compensated_targets_bring_the_real_robot_to_the_points(campaign):
    config, folder, data, validation_rms = campaign
    model = load_model(str(folder / "report" / "model.toml"))
    assert model.T_sensor_base is not None
    nominal = load_model(config.robot.model).model
    home = np.radians(config.robot.home_deg)
    # Intended points in the tracker's frame: ten points inside the calibrated cube.
    rng = np.random.default_rng(7)
    centre, half = np.array(config.campaign.cube_centre_mm), config.campaign.cube_edge_mm / 2
    p_base = centre + rng.uniform(-0.8 * half, 0.8 * half, (10, 3))
    p_tracker = apply(model.T_sensor_base, p_base)
    targets = folder / "targets.csv"
    targets.write_text(
        "name,x,y,z\n"
        + "".join(f"P{k},{x:.9f},{y:.9f},{z:.9f}\n" for k, (x, y, z) in enumerate(p_tracker))
    )
    out = folder / "joints.csv"
    seed = ",".join(repr(v) for v in config.robot.home_deg)
    run = _compensate(folder, targets, out, "--frame", "sensor", "--seed-deg", seed, "--json")
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    rows = list(csv.DictReader(out.open()))
    assert [r["name"] for r in rows] == [f"P{k}" for k in range(10)]
    q_comp = np.radians([[float(r[f"q{i}"]) for i in range(1, 7)] for r in rows])
    np.testing.assert_allclose([[float(r[c]) for c in "xyz"] for r in rows], p_tracker, atol=1e-6)

    # The nominal model's level: its joints for the same points, with the frame and the
    # target offset that fit it best to the campaign's calibration poses.
    cal = np.array([r == CALIBRATION for r in data.role])
    target_offset = model.target_offset
    fit = fit_rigid(
        target_kinematics(nominal, data.q[cal], target_offset).p, data.mean["tracker"][cal]
    )
    q_nom = compensate(
        nominal, target_offset, nominal, apply(invert(fit.T), p_tracker), None, home
    ).q

    measured = _measure(config, np.concatenate([q_comp, q_nom]))
    err_comp = np.linalg.norm(measured[:10] - p_tracker, axis=1)
    err_nom = np.linalg.norm(measured[10:] - p_tracker, axis=1)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    print(
        f"compensated: RMS {rms(err_comp):.4f} mm, max {err_comp.max():.4f} mm; "
        f"nominal: RMS {rms(err_nom):.4f} mm; campaign validation RMS {validation_rms:.4f} mm"
    )
    # From the nominal level to about the calibration's validation error.
    assert rms(err_nom) > 0.2
    assert rms(err_comp) < 0.25 * rms(err_nom)
    assert rms(err_comp) < 2.0 * validation_rms
    # The reported correction: where the nominal model puts the target at the
    # compensated joints, against the point (base frame of the calibrated model).
    p_nominal = target_kinematics(nominal, q_comp, target_offset, jacobian=False).p
    correction = np.linalg.norm(p_nominal - apply(invert(model.T_sensor_base), p_tracker), axis=1)
    assert summary["rms_correction_mm"] == pytest.approx(rms(correction), abs=1e-6)
    assert summary["max_residual_mm"] < 1e-6


def test_compensate_refuses_a_nominal_model_and_unreachable_targets(campaign, tmp_path):
    config, folder, _, _ = campaign
    targets = tmp_path / "t.csv"
    targets.write_text("name,x,y,z\nfar,9000,0,0\nnear,750,0,1000\n")
    out = tmp_path / "j.csv"
    run = cli(
        "compensate", "--model", config.robot.model, "--targets", str(targets), "--out", str(out)
    )
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "nominal model" in run.stderr
    run = _compensate(folder, targets, out)
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1
    assert "1 of 2 targets" in run.stderr and "far:" in run.stderr
    assert "nothing written" in run.stderr and not out.exists()
    targets.write_text("name,x,y,z,q1,q2\nP,750,0,1000,0,0\n")
    run = _compensate(folder, targets, out)
    assert run.returncode == 2 and "give all of q1" in run.stderr


def test_the_programs_joints_choose_the_configuration_and_keep_the_orientation(campaign, tmp_path):
    config, folder, data, _ = campaign
    model = load_model(str(folder / "report" / "model.toml"))
    nominal = load_model(config.robot.model).model
    q_today = data.q[:5]
    p = target_kinematics(nominal, q_today, model.target_offset, jacobian=False).p
    head = "name,x,y,z," + ",".join(f"q{i}" for i in range(1, 7))
    rows = [
        ",".join([f"T{k}", *(f"{v:.9f}" for v in p[k]), *(f"{v:.9f}" for v in np.degrees(q))])
        for k, q in enumerate(q_today)
    ]
    targets = tmp_path / "t.csv"
    targets.write_text(head + "\n" + "\n".join(rows) + "\n")
    out = tmp_path / "j.csv"
    run = _compensate(folder, targets, out, "--json")
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["orientation"] == "kept from the q columns"
    got = list(csv.DictReader(out.open()))
    q = np.radians([[float(r[f"q{i}"]) for i in range(1, 7)] for r in got])
    # Near today's joints, and the calibrated model's flange turned as the program's is.
    assert np.degrees(np.abs(q - q_today)).max() < 0.5
    reached = target_kinematics(model.model, q, model.target_offset, jacobian=False)
    assert np.abs(reached.p - p).max() < 1e-6
    R_today = flange_transforms(nominal, q_today)[:, :3, :3]
    turn = np.einsum("nji,njk->nik", R_today, reached.R_flange)
    assert np.allclose(turn, np.eye(3), atol=1e-9)
    # The Cartesian form is the nominal model's flange pose at the compensated joints.
    T = flange_transforms(nominal, q)
    flange = np.array([[float(r[f"flange_{c}"]) for c in "xyz"] for r in got])
    np.testing.assert_allclose(flange, T[:, :3, 3], atol=1e-6)
