"""``cellcal report``: a campaign's results out of the database."""

from __future__ import annotations

import click

from cellcal.commands.output import print_json
from cellcal.reports.folder import write_report
from cellcal.reports.html import report_html  # noqa: F401 - matplotlib: a missing extra is named at once
from cellcal.store.database import Store


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.4f}"


@click.command()
@click.option("--db", "db_path", required=True, help="Campaign database (read only).")
@click.option("--campaign", "campaign_id", type=int, help="Campaign id (default: the latest).")
@click.option("--out", "out_dir", required=True, help="Folder to write the report into.")
@click.option(
    "--compare-registration",
    "methods",
    is_flag=True,
    help="Also compare the registration methods on this campaign (the paper's Fig. 9).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def report(
    db_path: str, campaign_id: int | None, out_dir: str, methods: bool, as_json: bool
) -> None:
    """Write a campaign's report folder: index.html (the report: self-contained, figures
    inline), summary.json, model.toml, poses.csv, measurements-<sensor>.csv (the
    calibrate format), validation-<sensor>.csv."""
    store = Store(db_path, readonly=True)
    try:
        folder = write_report(store, campaign_id, out_dir, methods=methods)
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
