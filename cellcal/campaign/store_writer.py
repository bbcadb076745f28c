"""The store as a subscriber of the record stream: every pose record becomes one
transaction (the pose, its raw samples and their statistics), every event a row, the
start and end of a campaign its status. It is the stream's critical subscriber: if it cannot
write, the campaign stops (resumable) rather than count a pose it did not keep."""

from __future__ import annotations

from cellcal.campaign.records import (
    CampaignEnded,
    CampaignEvent,
    CampaignStarted,
    PoseStored,
    Record,
)
from cellcal.store.database import Store


class StoreWriter:
    def __init__(self, store: Store) -> None:
        self.store = store

    def __call__(self, record: Record) -> None:
        if isinstance(record, PoseStored):
            p = record.pose
            self.store.add_pose(
                record.campaign_id,
                idx=p.idx,
                role=p.role,
                region=p.region,
                target_mm=p.target_mm,
                planned_q=p.q,
                reached_q=record.reached_q,
                t_start=record.t_start,
                t_end=record.t_end,
                series=list(record.series),
            )
        elif isinstance(record, CampaignEvent):
            self.store.add_event(record.campaign_id, record.kind, record.message, record.pose_idx)
        elif isinstance(record, CampaignStarted):
            self.store.set_status(record.campaign_id, "running")
        elif isinstance(record, CampaignEnded):
            self.store.set_status(record.campaign_id, record.status)
