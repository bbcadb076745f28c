"""Session layouts cut from a real robot's calibration poses (benchmarks/real_data.py)
and the plain fit (benchmarks/plain_fit.py): the line is on a line as cellcal judges
it, the surface near one plane and not on a line, each session's rigid move changes
coordinates only, and the plain fit of cellcal's parameters on the UR5 predicts the
held-out poses as well as cellcal does."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from cellcal.calib.identification import calibrate
from cellcal.calib.observations import on_a_line
from cellcal.calib.validation import ErrorStats, validate_on
from tests.lazy import Lazy

BENCHMARKS = Path(__file__).parents[2] / "benchmarks"


def _load(name: str) -> ModuleType:
    """benchmarks/NAME.py, under its own name: real_data imports plain_fit beside it."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


class _Benchmark(Lazy):
    """A benchmark module (after the benchmark modules it imports, ``first``), loaded by
    the first test that reads it: they import scipy, which the parallel run's workers
    would otherwise each load as they collect."""

    def __init__(self, name: str, *first: str) -> None:
        super().__init__(name)
        self._first = first

    def _load(self) -> Any:
        for name in self._first:
            _load(name)
        return _load(self._module)


plain_fit: Any = _Benchmark("plain_fit")
layouts_module: Any = _Benchmark("session_layouts")
real_data: Any = _Benchmark("real_data", "plain_fit", "session_layouts")
#: benchmarks/real_data.py's robots (checked below), named here for the parametrisation
ROBOTS = ("ur5", "barrett-wam")


def test_the_robots_are_the_benchmarks():
    assert real_data.ROBOTS == ROBOTS


@pytest.fixture(scope="module", params=ROBOTS)
def layouts(request):
    robot = real_data.Robot.load(request.param)
    return robot, {s.name: s for s in real_data.session_layouts(robot.data.xyz)}


def test_sessions_split_the_poses(layouts):
    robot, lay = layouts
    assert tuple(lay) == real_data.LAYOUTS
    rows = np.concatenate([s.rows for s in lay.values()])
    assert np.array_equal(np.sort(rows), np.arange(len(robot.data.xyz)))


def test_the_line_session_is_on_a_line(layouts):
    robot, lay = layouts
    line = lay["line"]
    assert len(line.rows) >= 3
    for points in (robot.data.xyz[line.rows], real_data.moved(robot.data.xyz[line.rows], line.T)):
        found = on_a_line(points)
        assert found is not None
        assert found.along_mm > 200.0  # a line through the workspace, not a knot


def test_the_surface_session_is_near_one_plane_and_not_on_a_line(layouts):
    robot, lay = layouts
    points = robot.data.xyz[lay["surface"].rows]
    assert len(points) >= 20
    c = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(c, full_matrices=False)
    off = np.abs(c @ vt[2])
    assert off.max() <= 2 * layouts_module.PLANE_MM
    assert sv[2] < 0.05 * sv[1]  # flat, and spread in two directions ...
    assert on_a_line(points) is None  # ... so not on a line
    assert on_a_line(robot.data.xyz[lay["curve"].rows]) is None


def test_the_rigid_moves_change_coordinates_only(layouts):
    robot, lay = layouts
    for s in lay.values():
        R = s.T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert real_data.distance_change(robot.data.xyz, s.T) < 1e-9
    moved = real_data.moved(robot.data.xyz, lay["surface"].T)
    assert np.abs(moved - robot.data.xyz).max() > 100.0  # it did move them


def test_the_plain_fit_predicts_the_ur5_as_well_as_cellcal():
    robot = real_data.Robot.load("ur5")
    q, xyz = robot.data.q, robot.data.xyz
    res = calibrate(robot.nominal, q, xyz)
    after = validate_on(res, q, xyz, robot.val.q, robot.val.xyz).after.rms
    pf = plain_fit.plain_fit(robot.nominal, q, xyz, res.covariance_specs)
    plain = ErrorStats.of(robot.val.xyz - pf.predict(robot.val.q)).rms
    assert pf.success
    assert abs(plain - after) <= 0.1 * after
    assert pf.nfev > len(res.covariance_specs)  # the numeric Jacobian's evaluations count
    assert pf.seconds > 0 and pf.peak_bytes > 0
