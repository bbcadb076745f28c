"""Robot models: built-ins, the TOML structure, strictness, parallel-axis detection."""

from __future__ import annotations

import math

import pytest

from cellcal.calib.robot_model import ModelError, detect_parallel, model_from_dict, model_to_dict
from cellcal.files.models import builtin_names, load_model


def test_builtins_and_their_parallel_rows():
    assert builtin_names() == ["kuka-kr5-arc", "ur10e", "ur5e"]
    kr5 = load_model("kuka-kr5-arc").model
    assert kr5.dof == 6 and kr5.convention == "dh"
    assert kr5.parallel == (False, True, False, False, False, False)
    assert kr5.joints[1].a == 600.0 and kr5.joints[1].theta == pytest.approx(math.radians(-90))
    assert kr5.joints[2].q_min == pytest.approx(math.radians(-15))
    for ur in ("ur5e", "ur10e"):
        assert load_model(ur).model.parallel == (False, True, True, False, False, False)
    assert load_model("ur10e").model.joints[1].a == -612.7


def _table(**over):
    rows = [{"a": 0.0, "alpha": 90.0, "d": 100.0, "theta": 0.0} for _ in range(3)]
    data = {"name": "t", "convention": "dh", "joint": rows}
    data.update(over)
    return data


def test_round_trip_through_the_toml_structure():
    m = load_model("kuka-kr5-arc").model
    back = model_from_dict(model_to_dict(m))
    assert back == m
    assert model_to_dict(m)["joint"][2]["min"] == -15.0  # no 14.999999999999998


def test_tool_and_beta_keys():
    m = model_from_dict(_table(tool={"xyz": [1, 2, 3]}))
    assert list(m.target_offset) == [1.0, 2.0, 3.0]
    rows = _table()["joint"]
    rows[0]["beta"] = 0.5
    assert model_from_dict(_table(joint=rows)).joints[0].beta == pytest.approx(math.radians(0.5))


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"colour": "red"}, "unknown key 'colour'"),
        ({"convention": "xyz"}, "convention"),
        ({"joint": []}, r"\[\[joint\]\]"),
        ({"name": ""}, "name"),
        ({"tool": {"xyz": [1, 2]}}, "tool.xyz"),
        ({"tool": {"rpy": [1, 2, 3]}}, "tool"),
    ],
)
def test_bad_top_level(change, match):
    with pytest.raises(ModelError, match=match):
        model_from_dict(_table(**change), "m.toml")


@pytest.mark.parametrize(
    ("row", "match"),
    [
        ({"a": 1, "alpha": 0, "d": 0}, "joint 2: missing theta"),
        ({"a": "x", "alpha": 0, "d": 0, "theta": 0}, r"joint 2\.a: expected a number"),
        ({"a": 1, "alpha": 0, "d": 0, "theta": 0, "offset": 3}, "unknown key 'offset'"),
        ({"a": 1, "alpha": 0, "d": 0, "theta": 0, "min": 10, "max": -10}, "min must be below max"),
        ({"a": True, "alpha": 0, "d": 0, "theta": 0}, "expected a number"),
        ({"a": float("nan"), "alpha": 0, "d": 0, "theta": 0}, "not finite"),
    ],
)
def test_bad_joint_rows(row, match):
    rows = _table()["joint"]
    rows[1] = row
    with pytest.raises(ModelError, match=match):
        model_from_dict(_table(joint=rows), "m.toml")


def test_parallel_detection_threshold_and_conventions():
    rows = _table()["joint"]
    rows[0]["alpha"] = 0.9  # within 1° of parallel
    rows[1]["alpha"] = 1.1  # not
    m = model_from_dict(_table(joint=rows))
    assert m.parallel == (True, False, False)
    # The last DH row is the flange: never "between two axes".
    rows[2]["alpha"] = 0.0
    assert model_from_dict(_table(joint=rows)).parallel == (True, False, False)
    # MDH: row i carries α(i−1), between axes i−1 and i; row 1 never counts.
    mdh = model_from_dict(_table(joint=rows, convention="mdh"))
    assert mdh.parallel == (False, False, True)
    assert detect_parallel("mdh", mdh.joints) == mdh.parallel
