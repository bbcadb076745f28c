"""Acceptance checks: data and results that cannot be right are refused with the cause."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellcal.calib.acceptance import (
    CHECK_CONVERGENCE,
    CHECK_FOLLOWS,
    CHECK_REGISTRATION,
    CHECK_SPAN,
    CHECK_TOLERANCE,
    CHECK_UNITS,
)
from cellcal.calib.geometry import wrap_deg
from cellcal.calib.identification import calibrate
from cellcal.errors import AcceptanceError, InputError
from cellcal.files.models import builtin_names, load_model
from cellcal.mocks.robot_truth import TrueCell, measure
from tests.calib.simulated import NOISE_MM, paper_cube, well_spread

KR5 = load_model("kuka-kr5-arc").model
ALTERNATIVES = tuple(load_model(n).model for n in builtin_names())


def _refusal(q, m, model=KR5, **kw) -> AcceptanceError:
    with pytest.raises(AcceptanceError) as info:
        calibrate(model, q, m, alternatives=ALTERNATIVES, **kw)
    assert "\n" not in str(info.value)
    return info.value


def test_positions_in_metres_are_refused():
    d = well_spread("kuka-kr5-arc")
    r = _refusal(d.q, d.m / 1000.0)
    assert r.check == CHECK_UNITS and "metres" in r.message


def test_joint_readings_in_radians_are_refused():
    d = well_spread("kuka-kr5-arc")
    # The file's numbers are radians; read as degrees they became radians/57.3.
    r = _refusal(np.radians(d.q), d.m)
    assert r.check == CHECK_UNITS and "radians" in r.message


def test_a_target_that_does_not_follow_the_robot_is_refused():
    d = well_spread("kuka-kr5-arc")
    rng = np.random.default_rng(0)
    static = d.m[0] + rng.normal(0.0, 0.01, d.m.shape)
    r = _refusal(d.q, static)
    assert r.check == CHECK_FOLLOWS


def test_a_cube_typed_in_metres_is_refused():
    d = paper_cube(0.0)
    # All poses within 0.2 mm: the arm does not move.
    q = d.q[:1] + np.random.default_rng(1).normal(0.0, 1e-6, d.q.shape)
    m = d.m[:1] + np.random.default_rng(2).normal(0.0, 0.01, d.m.shape)
    r = _refusal(q, m)
    assert r.check == CHECK_SPAN and "metres" in r.message


def test_a_flipped_joint_sign_is_named():
    d = well_spread("kuka-kr5-arc")
    q = d.q.copy()
    q[:, 0] *= -1.0  # joint 1 has symmetric limits: the file is readable, the sign wrong
    r = _refusal(q, d.m)
    assert r.check == CHECK_REGISTRATION
    assert "joint 1 with the opposite sign" in r.message


def test_the_wrong_model_is_named():
    d = well_spread("ur10e")
    r = _refusal(d.q, d.m, model=load_model("ur5e").model)
    assert "the model ur10e" in r.message


def test_corrections_beyond_tolerances_are_refused_unless_accepted():
    d = well_spread("kuka-kr5-arc")
    joints = list(d.cell.model.joints)
    joints[1] = replace(joints[1], a=joints[1].a + 15.0)  # a2 15 mm longer than nominal
    cell = TrueCell(KR5.with_joints(tuple(joints)), d.cell.target_offset, d.cell.T_sensor_base)
    m = measure(cell, d.q, np.random.default_rng(3), NOISE_MM)
    r = _refusal(d.q, m)
    assert r.check == CHECK_TOLERANCE and re.search(r"a2 \+1[45]", r.message)
    res = calibrate(KR5, d.q, m, accept=True)
    assert any("accepted despite" in w and "a2" in w for w in res.warnings)


def test_no_convergence_is_diagnosed(monkeypatch):
    import cellcal.calib.levenberg as levenberg

    monkeypatch.setattr(levenberg, "PASSES_PER_PARAMETER", 0)  # every fit runs out of passes
    d = well_spread("kuka-kr5-arc")
    with pytest.raises(AcceptanceError) as info:
        calibrate(KR5, d.q, d.m)
    assert info.value.check == CHECK_CONVERGENCE


def test_fixed_orientation_keeps_the_target_offset_nominal_and_corrections_plausible():
    d = paper_cube(0.0)
    res = calibrate(KR5, d.q, d.m)
    assert {"target_offset_x", "target_offset_y", "target_offset_z"} <= set(res.unidentifiable)
    np.testing.assert_array_equal(res.target_offset, KR5.target_offset)
    for p in res.parameters:
        if p.kind != "target_offset":
            assert abs(p.value) < (2.0 if p.unit == "deg" else 10.0), p
    # Weakly determined parameters are named, not fitted to noise.
    weak = [p.name for p in res.parameters if p.at_nominal == "weak"]
    assert weak
    # The model still predicts at the measured orientation.
    err = res.predict(d.q_val) - d.m_val_true
    assert float(np.sqrt(np.mean(np.sum(err * err, axis=1)))) < 5 * NOISE_MM


def test_well_spread_data_leave_nothing_weak():
    d = well_spread("kuka-kr5-arc")
    res = calibrate(KR5, d.q, d.m)
    assert not res.identifiability.weak


def test_fix_pins_parameters():
    d = well_spread("kuka-kr5-arc")
    res = calibrate(KR5, d.q, d.m, fix=("a2", "beta2"))
    by = {p.name: p for p in res.parameters}
    assert by["a2"].at_nominal == "fixed" and by["a2"].value == 0.0
    assert not by["beta2"].identified
    frames_only = calibrate(KR5, d.q, d.m, fix=("kinematics",))
    assert set(frames_only.identified) == {"target_offset_x", "target_offset_y", "target_offset_z"}
    assert frames_only.rms_after == pytest.approx(frames_only.rms_before, rel=1e-6)
    with pytest.raises(InputError, match="no such parameter"):
        calibrate(KR5, d.q, d.m, fix=("a9",))


@given(st.floats(-1e12, 1e12, allow_nan=False))
def test_wrapped_angles_lie_in_the_half_open_interval(a):
    w = wrap_deg(a)
    assert -180.0 < w <= 180.0
    assert math.isclose(math.cos(math.radians(w)), math.cos(math.radians(a % 360.0)), abs_tol=1e-6)


def test_a_target_that_never_moves_does_not_follow_the_robot() -> None:
    """Every measurement the same point while the robot moves (a twin or a sensor that
    does not see this robot): refused as a target that does not follow the robot (exit
    3), not as degenerate geometry (exit 2), which points on a line still are."""
    from cellcal.errors import DegenerateGeometryError

    q = well_spread("kuka-kr5-arc", 4, 30).q
    still = np.tile([1500.0, 20.0, 300.0], (30, 1))
    with pytest.raises(AcceptanceError, match=f"^{CHECK_FOLLOWS}: the measured target moves 0"):
        calibrate(KR5, q, still)
    line = np.outer(np.arange(30.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateGeometryError):
        calibrate(KR5, q, line)
