"""Campaign results out of the database: the campaign list and the report folder.

The report folder holds ``summary.json`` (the analysis' summary with the campaign's
facts), ``model.toml`` (the calibrated model, as ``calibrate --out`` writes it),
``poses.csv`` (every stored pose: plan index, role, region, reached joints, each
sensor's mean and sample count), one ``measurements-<sensor>.csv`` per sensor (the
calibration poses in the ``calibrate`` format, with the σ of each mean as the analysis
weighted it, so that ``cellcal calibrate`` reads it back to the same result), one
``validation-<sensor>.csv`` (the validation poses, for ``--validate``), and
``index.html``: the report page, self-contained, figures inline (``report_html``).
Files are written atomically; the database is only read.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal import __version__
from cellcal.calib.geometry import Array, apply, invert
from cellcal.campaign.analysis import mean_sigma
from cellcal.campaign.kinds import DEFAULT_KIND, shown_kinds
from cellcal.campaign.plan import CALIBRATION, VALIDATION
from cellcal.campaign.pose_conditions import pose_conditions
from cellcal.errors import CampaignError, InputError
from cellcal.files.measurements import CONDITION_RANGES
from cellcal.files.models import write_atomically
from cellcal.files.outputs import check_output_file
from cellcal.reports.data import report_data, with_planned_payloads
from cellcal.store.database import CampaignRow, PoseData, Store
from cellcal.store.queries import CampaignListing


def list_campaigns(store: Store) -> list[CampaignListing]:
    """Every campaign, oldest first, with its kind (``calibration``, ``iso9283``)."""
    kinds = shown_kinds(store)
    return [
        dataclasses.replace(row, kind=kinds.get(row.id, DEFAULT_KIND))
        for row in store.campaign_listings()
    ]


def latest_campaign(store: Store) -> int:
    cid = store.latest_campaign_id()
    if cid is None:
        raise CampaignError(f"{store.path}: no campaign in this database")
    return cid


#: The measurement file's columns of what error terms read (cellcal.files.measurements).
CONDITION_COLUMNS = tuple(CONDITION_RANGES)


def _number(v: float) -> str:
    """Shortest text that reads back to the same float."""
    return repr(float(v)) if math.isfinite(v) else ""


def measurements_csv(data: PoseData, sensor: str, role: str) -> str:
    """The ``calibrate`` format: name (plan index), q (deg), x, y, z and sx, sy, sz (mm),
    and what the error terms read where the campaign recorded it for every one of these
    poses: ``time_s``, ``temperature_c`` (the robot's joints, else the tracker's air) and
    ``payload_kg`` — so a calibration from this file finds the same drift and compliance
    as the campaign's."""
    dof = data.q.shape[1]
    mean, sig = data.mean[sensor], mean_sigma(data, sensor)
    mask: Array = (np.array(data.role) == role) & np.isfinite(mean).all(axis=1)
    rows = np.flatnonzero(mask)
    conditions = pose_conditions(data, mask) if len(rows) else None
    extra: list[tuple[str, Array]] = []
    for name in CONDITION_COLUMNS if conditions is not None else ():
        column = conditions.column(name) if conditions is not None else None
        if column is not None:
            extra.append((name, column))
    head = ["name", *(f"q{i}" for i in range(1, dof + 1)), "x", "y", "z", "sx", "sy", "sz"]
    lines = [",".join([*head, *(name for name, _ in extra)])]
    for j, k in enumerate(rows):
        values = [*np.degrees(data.q[k]), *mean[k], *sig[k], *(v[j] for _, v in extra)]
        lines.append(",".join([str(int(data.idx[k])), *(_number(v) for v in values)]))
    return "\n".join(lines) + "\n"


def poses_csv(data: PoseData) -> str:
    dof = data.q.shape[1]
    sensors = sorted(data.mean)
    head = ["idx", "role", "region", *(f"q{i}" for i in range(1, dof + 1))]
    for s in sensors:
        head += [f"{s}_x", f"{s}_y", f"{s}_z", f"{s}_n"]
    lines = [",".join(head)]
    for k, idx in enumerate(data.idx):
        row = [str(int(idx)), data.role[k], data.region[k]]
        row += [_number(v) for v in np.degrees(data.q[k])]
        for s in sensors:
            row += [_number(v) for v in data.mean[s][k]] + [str(int(data.n[s][k]))]
        lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def plan_text(config_json: str) -> str:
    """How the campaign chose its calibration poses, from its stored configuration: the
    cube's grid, or N D- or I-optimal poses of the candidates, the cube's or those drawn
    over the workspace box (``cellcal plan``)."""
    try:
        campaign = json.loads(config_json).get("campaign", {})
    except (ValueError, AttributeError):
        campaign = {}
    if not isinstance(campaign, dict):
        campaign = {}
    n = campaign.get("optimal_poses") or 0
    if n:
        criterion = campaign.get("optimal_criterion", "D")
        where = (
            "candidates drawn over the workspace box"
            if campaign.get("region") == "workspace"
            else "the cube's candidates"
        )
        return f"{n} {criterion}-optimal calibration poses of {where}"
    grid = campaign.get("grid")
    if isinstance(grid, list) and grid:
        return "the cube's grid, " + " × ".join(str(k) for k in grid) + " points"
    return "the cube's grid"


#: The roles of an ISO 9283 test's poses (``iso_campaign.BEFORE``, ``AFTER``).
ISO_STAGES = ("iso-before", "iso-after")


def is_iso_test(store: Store, campaign_id: int, summary: dict[str, Any] | None) -> bool:
    """An ISO 9283 test (``cellcal iso9283``), not a calibration campaign: its summary
    says so, or (interrupted) its first event does."""
    if summary is not None and "iso9283" in summary:
        return True
    return store.has_event(campaign_id, "iso9283")


def iso_plan_text(summary: dict[str, Any] | None, n_poses: int) -> str:
    """What an ISO 9283 test's poses were."""
    s = summary or {}
    cycles = s.get("cycles") or n_poses // (5 * len(ISO_STAGES))
    nominal = s.get("nominal_model") or "the nominal model"
    calibrated = s.get("calibrated_model") or "the calibrated model"
    return (
        f"ISO 9283 AP/RP test: the standard's five points P1…P5, {cycles} cycles with the "
        f"joints of the nominal model ({nominal}), then {cycles} with those of the "
        f"calibrated model ({calibrated})"
    )


def iso_csv(
    store: Store, campaign_id: int, data: PoseData, sensor: str, summary: dict[str, Any] | None
) -> str:
    """An ISO 9283 test's visits as one sensor measured them, one row per point and cycle,
    readable by ``cellcal calibrate`` (``name``, ``q1..qN``, ``x,y,z``, ``sx,sy,sz``: the
    sensor's mean in its frame) with ``stage``, ``point``, ``cycle``, the commanded
    position ``commanded_x,_y,_z`` (mm, robot base frame) and, for the reference sensor,
    the attained position ``attained_x,_y,_z`` (the mean brought into the calibrated
    model's base frame: what AP and RP are computed from)."""
    s = summary or {}
    T = s.get("T_sensor_base")
    attained = None
    if T is not None and sensor == s.get("reference_sensor"):
        attained = apply(invert(np.array(T, dtype=np.float64)), data.mean[sensor])
    targets = store.pose_targets(campaign_id)
    per_stage = max(store.campaign(campaign_id).n_poses // len(ISO_STAGES), 1)
    dof = data.q.shape[1]
    head = ["name", "stage", "point", "cycle", "commanded_x", "commanded_y", "commanded_z"]
    head += [*(f"q{i}" for i in range(1, dof + 1)), "x", "y", "z", "sx", "sy", "sz"]
    if attained is not None:
        head += ["attained_x", "attained_y", "attained_z"]
    lines = [",".join(head)]
    mean, sig = data.mean[sensor], mean_sigma(data, sensor)
    for k, idx in enumerate(data.idx):
        if not np.isfinite(mean[k]).all():
            continue
        cycle = (int(idx) % per_stage) // 5 + 1
        row = [str(int(idx)), data.role[k], data.region[k], str(cycle)]
        row += [_number(v) if v is not None else "" for v in targets[int(idx)]]
        row += [_number(v) for v in [*np.degrees(data.q[k]), *mean[k], *sig[k]]]
        if attained is not None:
            row += [_number(v) for v in attained[k]]
        lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def _timeline(store: Store, row: CampaignRow, iso: bool) -> tuple[float, dict[str, str]]:
    """The campaign's dwell (s), and the page's rows about what it did: its plan (an ISO
    9283 test: its cube), when it was created and its poses stored (UTC), its acquisition
    time on the campaign's clock (simulated seconds in mock mode)."""
    times = store.campaign_times(row.id)
    roles = store.stored_by_role(row.id).items()
    out = {"created": times.created}
    c = json.loads(row.config_json).get("campaign", {})
    with contextlib.suppress(KeyError, TypeError, ValueError):
        centre = ", ".join(f"{float(v):g}" for v in c["cube_centre_mm"])
        edge = float(c["cube_edge_mm"])
        if iso:
            out["ISO 9283 test cube"] = (
                f"{edge:g} mm edge at ({centre}) mm; P1 its centre, P2…P5 on its diagonal "
                "plane x = y; flange at its home orientation"
            )
        else:
            grid = "×".join(str(int(k)) for k in c["grid"])
            out["plan"] = (
                f"{grid} cube of {edge:g} mm at ({centre}) mm, wrist turned "
                f"up to {float(c['orientation_variation_deg']):g}° per pose"
            )
    out["poses stored per role"] = ", ".join(f"{r}: {n}" for r, n in roles) or "none"
    span = times.poses
    if span is not None:
        out["first pose stored"] = span.first_stored
        out["last pose stored"] = span.last_stored
        out["acquisition (campaign clock)"] = f"{(span.t_end - span.t_start) / 60:.1f} min"
    return times.dwell_s, out


@dataclass(frozen=True)
class ReportFolder:
    campaign_id: int
    folder: str
    files: tuple[str, ...]
    analysed: bool


def report_folder(db_path: str | Path, campaign_id: int) -> Path:
    """Where the service writes a campaign's report: ``reports/campaign-N`` beside the
    database."""
    return Path(db_path).resolve().parent / "reports" / f"campaign-{campaign_id}"


def write_report(
    store: Store, campaign_id: int | None, out: str | Path, *, methods: bool = False
) -> ReportFolder:
    """Write the report folder of a campaign (default: the latest) into ``out``;
    ``methods``: compare the registration methods too (the paper's Fig. 9)."""
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out {folder}: exists and is not a folder")
    cid = latest_campaign(store) if campaign_id is None else campaign_id
    row = store.campaign(cid)
    data = with_planned_payloads(store, cid, store.pose_data(cid))
    summary = store.latest_report(cid)
    model = store.latest_model_toml(cid)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {folder}: cannot create ({exc.strerror})") from None
    facts: dict[str, Any] = {
        "campaign_id": cid,
        "database": store.path,
        "status": row.status,
        "model": row.model,
        "sensors": list(row.sensors),
        "n_poses": row.n_poses,
        "poses_stored": len(data.idx),
        "samples_per_pose": row.samples_per_pose,
        "mock": row.mock,
        "plan": plan_text(row.config_json),
        "cellcal_version": __version__,
        "acquired_with": store.acquired_with(cid),
    }
    iso = is_iso_test(store, cid, summary)
    if iso:
        facts["plan"] = iso_plan_text(summary, row.n_poses)
    files: dict[str, str] = {
        "summary.json": json.dumps({**facts, "summary": summary}, indent=2) + "\n",
        "poses.csv": poses_csv(data),
    }
    check = summary is not None and summary.get("kind") == "check"
    if check:
        facts["plan"] = f"{row.n_poses} check poses in the cube"
    for sensor in sorted(data.mean):
        if check:
            files[f"measurements-{sensor}.csv"] = measurements_csv(data, sensor, "check")
            continue
        if iso:  # every visit; there are no calibration or validation poses
            files[f"measurements-{sensor}.csv"] = iso_csv(store, cid, data, sensor, summary)
            continue
        files[f"measurements-{sensor}.csv"] = measurements_csv(data, sensor, CALIBRATION)
        files[f"validation-{sensor}.csv"] = measurements_csv(data, sensor, VALIDATION)
    if model is not None:
        files["model.toml"] = model
    dwell_s, timeline = _timeline(store, row, iso)
    page_facts = {**facts, "dwell_s": dwell_s, "iso9283": iso}
    data_for_page = report_data(store, cid, page_facts, methods=methods and not iso)
    from cellcal.reports.html import report_html  # matplotlib: loaded for a page only

    files["index.html"] = report_html(data_for_page, timeline)
    for name in files:  # a device, FIFO or folder in the way: refused before any is written
        check_output_file(folder / name)
    for name, text in files.items():
        write_atomically(folder / name, text)
    return ReportFolder(cid, str(folder), tuple(files), summary is not None)
