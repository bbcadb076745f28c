"""The campaign the status shows at start-up, as the database has it: the campaign held
(paused or interrupted), else the last one that ran, with its last stored poses as the
event stream sends them and, when it ended complete or refused, its end."""

from __future__ import annotations

from typing import Any

from cellcal.service.control import RECENT_POSES, sigma_mm
from cellcal.store.database import Store


def _r4(values: list[float | None]) -> list[float | None]:
    return [None if v is None else round(float(v), 4) for v in values]


def stored_poses(store: Store, campaign_id: int) -> list[dict[str, Any]]:
    """A campaign's last stored poses (oldest first) as the event stream sends them."""
    poses = store.last_poses(campaign_id, RECENT_POSES)
    planned = store.campaign(campaign_id).n_poses
    for p in poses:
        p["planned"] = planned
        for key in ("target_mm", "planned_q_deg", "reached_q_deg"):
            p[key] = _r4(p[key])
        for s in p["sensors"].values():
            s["sigma_mm"] = sigma_mm(s["std_mm"])  # of the values stored, as when live
            s["mean_mm"], s["std_mm"] = _r4(s["mean_mm"]), _r4(s["std_mm"])
    return poses


def campaign_view(
    store: Store, held: int | None
) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any] | None] | None:
    """What the status shows at start-up, from the database: the campaign held (paused or
    interrupted), else the last one that ran (none: None); with its last stored poses
    and, when it ended complete or refused, its end."""
    if held is None:
        held = store.last_started_campaign()
        if held is None:
            return None
    c = store.campaign(held)
    poses = stored_poses(store, held)
    roles = {role: {"stored": n} for role, n in store.stored_by_role(held).items()}
    view = {"id": held, "status": c.status, "phase": c.status, "stored": store.pose_count(held)}
    view.update(planned=c.n_poses, roles=roles)
    if poses:  # the last pose stored
        last = poses[-1]
        view.update({k: last[k] for k in ("role", "region", "target_mm", "planned_q_deg")})
        view.update(pose_idx=last["idx"], reached_idx=last["idx"])
        view.update(reached_q_deg=last["reached_q_deg"])
    end: dict[str, Any] | None = None
    if c.status in ("complete", "refused"):
        message = store.last_event(held, "refused") if c.status == "refused" else "complete"
        end = {"campaign_id": held, "status": c.status, "stored": view["stored"]}
        end.update(planned=c.n_poses, message=message or c.status)
        summary = store.latest_report(held) if c.status == "complete" else None
        if summary is not None and "validation_before" in summary:  # a calibration's
            before, after = summary["validation_before"], summary["validation_after"]
            end["validation_mm"] = {
                "before": {"rms": before["rms_mm"], "max": before["max_mm"]},
                "after": {"rms": after["rms_mm"], "max": after["max_mm"]},
                "improvement_pct": summary["improvement_pct"],
            }
    return view, poses, end
