"""The target offset's names (issue 30): ``target_offset_x/y/z`` and ``target_rotation_*``
in what cellcal writes, while a calibrated model or a database written with the earlier
names (``tool_x`` …, kind ``tool``) still reads and shows the offset's value."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from cellcal.calib.error_model import parameter_specs
from cellcal.files.models import load_model


def _doc(kind: str, name: str) -> dict[str, Any]:
    fit = {"n_points": 80, "rms_before_mm": 1.0, "rms_after_mm": 0.01, "sigma0": 1.0}
    fit["condition_number"] = 12.0
    row = {"name": name, "joint": 0, "kind": kind, "unit": "mm", "identified": False}
    row |= {"value": 120.25, "std": None, "at_nominal": "fixed"}
    return {"fit": fit, "parameter": [row]}


def _report(doc: dict[str, Any]) -> Any:
    """What the page's parameter section reads of a report (no figures to draw)."""
    return SimpleNamespace(model=doc, summary=None, singular_values=())


def _parameters(report: Any, salt: str) -> Any:
    # the report's page loads matplotlib: when a test shows it, not at collection
    from cellcal.reports.html import _parameters as parameters

    return parameters(report, salt)


def test_the_offsets_parameters_are_named_target_offset():
    model = load_model("kuka-kr5-arc").model
    specs = parameter_specs(model, orientation=True)
    offset = [s.name for s in specs if s.kind == "target_offset"]
    rotation = [s.name for s in specs if s.kind == "target_rotation"]
    assert offset == ["target_offset_x", "target_offset_y", "target_offset_z"]
    assert rotation == ["target_rotation_x", "target_rotation_y", "target_rotation_z"]
    assert not [s.name for s in specs if "tool" in s.name or "tool" in s.kind]


def test_a_report_shows_an_offset_stored_under_either_name():
    """A pinned offset keeps its value in the report's table, whichever name its row has;
    any other parameter left at nominal shows "0 (nominal kept)"."""
    for kind, name in (("target_offset", "target_offset_z"), ("tool", "tool_z")):
        page = _parameters(_report(_doc(kind, name)), "s")
        assert "+120.25000" in page and "0 (nominal kept)" not in page, kind
    page = _parameters(_report(_doc("a", "a2")), "s")
    assert "0 (nominal kept)" in page and "+120.25000" not in page
