"""Targets on one surface: a model fitted to it may predict worse than nominal away from
it (a real UR5's surface session did), so the calibration says so."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cellcal.calib.identification import calibrate, on_a_surface
from cellcal.files.measurements import read_measurements
from cellcal.files.models import load_model

UR5 = Path(__file__).parents[1] / "data" / "real" / "ur5"


def test_planes_are_surfaces_and_volumes_are_not():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-300, 300, (50, 2)), rng.normal(0, 2.0, 50)]
    said = on_a_surface(plane)
    assert said is not None and "mm RMS off a plane" in said
    off = float(said.split("(")[1].split(" mm")[0])
    assert 1.5 < off < 2.5  # the plane's 2 mm of scatter
    cube = rng.uniform(-100, 100, (50, 3))
    assert on_a_surface(cube) is None
    assert on_a_surface(plane[:3]) is None  # too few to tell


def test_a_real_surface_session_is_warned_and_the_whole_set_is_not():
    nominal = load_model(str(UR5 / "model.toml")).model
    data = read_measurements(UR5 / "measurements.csv", nominal.dof)
    xyz = data.xyz
    # the source's poses form a jittered grid: its fullest layer in z is a surface
    layers, counts = np.unique(np.round(xyz[:, 2] / 20.0), return_counts=True)
    rows = np.flatnonzero(np.abs(xyz[:, 2] - 20.0 * layers[np.argmax(counts)]) < 10.0)
    assert len(rows) > 40
    res = calibrate(nominal, data.q[rows], xyz[rows], accept=True)
    assert any("lie near one surface" in w for w in res.warnings)
    whole = calibrate(nominal, data.q, xyz)
    assert not any("surface" in w for w in whole.warnings)
