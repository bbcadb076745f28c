"""ISO 9283's AP and RP on positions whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.calib.iso9283 import CYCLES, iso_points, point_result, pose_characteristics
from cellcal.errors import InputError


def test_the_points_lie_on_the_diagonal_plane_a_tenth_from_the_corners():
    p = iso_points(np.array([750.0, 0.0, 1000.0]), 200.0)
    assert p.shape == (5, 3)
    np.testing.assert_allclose(p[0], [750.0, 0.0, 1000.0])
    rel = p[1:] - p[0]
    # On the plane x = y (through the centre) of the cube's axes.
    np.testing.assert_allclose(rel[:, 0], rel[:, 1])
    # A tenth of the space diagonal (200·√3 mm) from each corner: 0.4 of it from the centre.
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), 0.4 * 200.0 * np.sqrt(3))
    with pytest.raises(InputError):
        iso_points(np.zeros(3), 0.0)


def test_ap_is_the_barycentres_offset_and_rp_the_spread():
    rng = np.random.default_rng(1)
    c = np.array([100.0, 200.0, 300.0])
    offset = np.array([0.3, -0.4, 0.0])  # AP 0.5 mm
    x = c + offset + rng.normal(scale=0.01, size=(CYCLES, 3))
    r = point_result("P1", c, x)
    assert r.ap == pytest.approx(np.linalg.norm(x.mean(axis=0) - c))
    assert r.ap == pytest.approx(0.5, abs=0.01)
    dist = np.linalg.norm(x - x.mean(axis=0), axis=1)
    assert r.rp == pytest.approx(dist.mean() + 3 * dist.std(ddof=1))
    # Isotropic σ = 0.01 mm: l follows a Maxwell law, mean 0.016 and σ 0.0067 mm.
    assert 0.02 < r.rp < 0.055
    # Exactly repeated positions: RP 0, AP the offset.
    same = point_result("P2", c, np.tile(c + offset, (5, 1)))
    assert same.rp == pytest.approx(0.0, abs=1e-12) and same.ap == pytest.approx(0.5)


def test_every_point_of_every_cycle_is_used():
    c = iso_points(np.zeros(3), 100.0)
    x = np.broadcast_to(c, (CYCLES, 5, 3)).copy()
    x[:, 3] += [0.0, 0.0, 1.0]
    out = pose_characteristics(c, x)
    assert [r.name for r in out] == ["P1", "P2", "P3", "P4", "P5"]
    assert [round(r.ap, 9) for r in out] == [0.0, 0.0, 0.0, 1.0, 0.0]
    assert all(r.n == CYCLES for r in out)
    with pytest.raises(InputError):
        pose_characteristics(c, x[:, :4])
