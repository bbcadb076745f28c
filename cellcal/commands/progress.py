"""A campaign's progress on stderr, as ``cellcal run`` (``check``, ``iso9283``) shows
it: subscribers of the campaign's record stream, a rich bar on a terminal, else plain
lines; the kind's own words for the analysis that follows the last pose."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from cellcal.campaign.kinds import all_kinds

if TYPE_CHECKING:
    from cellcal.campaign.records import Record


def analysing(kind: str) -> str:
    """What follows the last pose of a campaign of ``kind``, said as it begins (the
    analysis takes seconds)."""
    found = all_kinds().get(kind)
    return found.analysing if found is not None else "every pose stored: analysing…"


class LineProgress:
    """Plain log lines on stderr (no terminal): every 10th pose and the last; a
    subscriber of the campaign's record stream."""

    def __init__(self) -> None:
        self._analysing = analysing("calibration")

    def __call__(self, record: Record) -> None:
        from cellcal.campaign.records import CampaignStarted, PoseStored

        if isinstance(record, CampaignStarted):
            self._analysing = analysing(record.kind)
            click.echo(f"acquiring {record.total - record.done} of {record.total} poses", err=True)
        elif isinstance(record, PoseStored) and (
            record.done % 10 == 0 or record.done == record.total
        ):
            p = record.pose
            click.echo(f"pose {record.done}/{record.total} stored ({p.role}, {p.region})", err=True)
            if record.done == record.total:
                click.echo(self._analysing, err=True)


class BarProgress:
    """A rich progress bar on a terminal; a subscriber of the campaign's record stream."""

    def __init__(self) -> None:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeRemainingColumn,
        )

        self._bar = Progress(
            TextColumn("[bold]acquiring"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.description}"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self._task = self._bar.add_task("", total=1)
        self._analysing = analysing("calibration")

    def __call__(self, record: Record) -> None:
        from cellcal.campaign.records import CampaignEnded, CampaignStarted, PoseStored

        if isinstance(record, CampaignStarted):
            self._analysing = analysing(record.kind)
            self._bar.update(self._task, total=record.total, completed=record.done)
            self._bar.start()
        elif isinstance(record, PoseStored):
            p = record.pose
            self._bar.update(self._task, completed=record.done, description=f"{p.role} {p.region}")
            if record.done == record.total:
                self.close()
                click.echo(self._analysing, err=True)
        elif isinstance(record, CampaignEnded):
            self.close()

    def close(self) -> None:
        self._bar.stop()
