"""``cellcal report`` and ``cellcal campaign list``: campaign results out of the database."""

from __future__ import annotations

import click

from cellcal.commands.output import print_json
from cellcal.daemon.report import list_campaigns, write_report
from cellcal.daemon.store import Store
from cellcal.errors import InputError


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.4f}"


@click.command()
@click.option("--db", "db_path", required=True, help="Campaign database (read only).")
@click.option("--campaign", "campaign_id", type=int, help="Campaign id (default: the latest).")
@click.option("--out", "out_dir", required=True, help="Folder to write the report into.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def report(db_path: str, campaign_id: int | None, out_dir: str, as_json: bool) -> None:
    """Write a campaign's report folder: summary.json, model.toml, poses.csv,
    measurements-<sensor>.csv (the calibrate format), validation-<sensor>.csv, index.html."""
    store = Store(db_path, readonly=True)
    try:
        folder = write_report(store, campaign_id, out_dir)
    finally:
        store.close()
    if as_json:
        print_json(
            {
                "campaign_id": folder.campaign_id,
                "out": folder.folder,
                "files": list(folder.files),
                "analysed": folder.analysed,
            }
        )
        return
    click.echo(f"report of campaign {folder.campaign_id} in {folder.folder}:")
    for name in folder.files:
        click.echo(f"  {name}")
    if not folder.analysed:
        click.echo("no analysis is stored for this campaign (interrupted or refused)")


@click.group()
def campaign() -> None:
    """Campaigns in a database."""


@campaign.command("list")
@click.option("--db", "db_path", help="Campaign database (read only).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def list_command(db_path: str | None, as_json: bool) -> None:
    """Campaigns with status, poses stored and result."""
    if db_path is None:
        raise InputError("give --db FILE (asking a running service is not available yet)")
    store = Store(db_path, readonly=True)
    try:
        rows = list_campaigns(store)
    finally:
        store.close()
    if as_json:
        print_json({"database": db_path, "campaigns": [r.as_dict() for r in rows]})
        return
    click.echo(
        f"{'id':>4}  {'created (UTC)':<19} {'status':<12} {'poses':>11}  {'RMS before':>11}"
        f"  {'RMS after':>10}  model / sensors"
    )
    for r in rows:
        created = r.created[:19].replace("T", " ")
        click.echo(
            f"{r.id:>4}  {created:<19} {r.status:<12} {r.stored:>5} / {r.n_poses:<4} "
            f"{_fmt(r.rms_before_mm):>11}  {_fmt(r.rms_after_mm):>10}  "
            f"{r.model} / {', '.join(r.sensors)}"
        )
