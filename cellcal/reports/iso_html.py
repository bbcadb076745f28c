"""The report page's section of an ISO 9283 test: AP and RP of each point, before and
after calibration."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cellcal.reports.html_parts import esc, mm_text, table


def _xyz(v: Sequence[float]) -> list[str]:
    return [mm_text(float(x)) for x in v]


def iso9283_section(s: dict[str, Any]) -> str:
    """An ISO 9283 test: AP and RP of each point before and after calibration, then per
    stage the commanded points, barycentres, AP components, l̄, S_l and RP."""
    iso = s["iso9283"]
    stages = list(iso)
    points = [p["point"] for p in iso[stages[0]]["points"]]
    rows = []
    for k, name in enumerate(points):
        row: list[object] = [name]
        row += [mm_text(iso[st]["points"][k]["ap_mm"]) for st in stages]
        row += [mm_text(iso[st]["points"][k]["rp_mm"]) for st in stages]
        rows.append(row)
    head = ["point", *(f"AP {st}" for st in stages), *(f"RP {st}" for st in stages)]
    sources = "; ".join(f"{st}: joints from the {iso[st]['joints_from']}" for st in stages)
    n = iso[stages[0]]["points"][0]["n"]
    reference = s.get("reference_sensor")
    parts = [
        "<h2>ISO 9283 pose accuracy (AP) and repeatability (RP), mm</h2>",
        f"<p>{n} cycles through the standard's five points P1…P5; {esc(sources)}. "
        "Attained positions: the "
        + (f"{esc(reference)}'s" if reference else "reference sensor's")
        + " mean at each visit, in the calibrated model's base frame. AP = ‖x̄ − c‖ "
        "(x̄ the barycentre of the attained positions, c the commanded point), "
        "RP = l̄ + 3·S_l (ISO 9283, 7.2.1 and 7.2.2); position only. Every visit (stage, "
        "point, cycle, commanded point, joints, the sensor's mean and the attained "
        "position) is in measurements-&lt;sensor&gt;.csv, at full precision.</p>",
        table(head, rows, ident="iso-summary"),
        "<h3>Commanded points (robot base frame, mm)</h3>",
        table(
            ["point", "x", "y", "z"],
            [[p["point"], *_xyz(p["commanded_mm"])] for p in iso[stages[0]]["points"]],
            ident="iso-commanded",
        ),
    ]
    for st in stages:
        parts.append(
            f"<h3>{esc(st)}: joints from the {esc(iso[st]['joints_from'])} "
            f"(barycentre x̄ and AP components x̄ − c, mm)</h3>"
        )
        detail = [
            [
                p["point"],
                *_xyz(p["barycentre_mm"]),
                *_xyz(p["ap_xyz_mm"]),
                mm_text(p["ap_mm"]),
                mm_text(p["l_mean_mm"]),
                mm_text(p["s_l_mm"]),
                mm_text(p["rp_mm"]),
                p["n"],
            ]
            for p in iso[st]["points"]
        ]
        head = ["point", "x̄", "ȳ", "z̄", "APx", "APy", "APz", "AP", "l̄", "S_l", "RP", "n"]
        parts.append(table(head, detail, ident=st))
    return "".join(parts)
