"""``cellcal iso9283``: the ISO 9283 pose accuracy and repeatability test, before and
after calibration — ``cellcal run --kind iso9283`` under its own name: the same runner,
the same campaign and progress on stderr, its result printed as the test's."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from cellcal.campaign.iso9283_kind import CYCLE_COUNT, MODEL
from cellcal.commands.output import TIME_SCALE, print_json
from cellcal.commands.run import CampaignRun, option_type, run_kind

if TYPE_CHECKING:
    from cellcal.campaign.runner import CampaignOutcome


@click.command("iso9283")
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option("--mock", is_flag=True, help="Run against the twins of the simulated cell.")
@click.option(
    "--model", "model_spec", required=True, help="The calibrated model (a campaign's model.toml)."
)
@click.option("--db", "db_path", help="Database (default: storage.database of the config).")
@click.option(
    "--cycles",
    type=option_type(CYCLE_COUNT),
    default=CYCLE_COUNT.default,
    show_default=True,
    help=f"Cycles through the five points (the standard: {CYCLE_COUNT.default}).",
)
@click.option("--time-scale", type=TIME_SCALE, default=0.0, help="Mock mode: wall s per s.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def iso9283(
    config_path: str | None,
    mock: bool,
    model_spec: str,
    db_path: str | None,
    cycles: int,
    time_scale: float,
    as_json: bool,
) -> None:
    """ISO 9283 pose accuracy (AP) and repeatability (RP) at the standard's five points
    of the campaign's cube: with the nominal model's joints, then the calibrated model's.
    Every sample is stored in the database like a campaign's; an interrupted test goes
    on with `cellcal run --resume ID`."""
    run_kind(
        CampaignRun(
            kind="iso9283",
            given={MODEL.name: model_spec, CYCLE_COUNT.name: cycles},
            config_path=config_path,
            mock=mock,
            db_path=db_path,
            time_scale=time_scale if mock else None,
            as_json=as_json,
        )
    )


def print_outcome(out: CampaignOutcome, folder: str | None, as_json: bool) -> None:
    """An ISO 9283 test's result: its JSON, or AP and RP per point, before and after."""
    from cellcal.campaign.iso9283_kind import AFTER, BEFORE, STAGES, IsoOutcome

    iso = out.result
    assert isinstance(iso, IsoOutcome)
    if as_json:
        print_json(iso.to_dict() if folder is None else {**iso.to_dict(), "report": folder})
        return
    click.echo(
        f"ISO 9283 test (campaign {iso.campaign_id} in {iso.db_path}), {iso.cycles} cycles, mm:"
    )
    click.echo(f"  {'point':<6}{'AP before':>11}{'AP after':>11}{'RP before':>11}{'RP after':>11}")
    for b, a in zip(iso.results[BEFORE], iso.results[AFTER], strict=True):
        click.echo(f"  {b.name:<6}{b.ap:11.4f}{a.ap:11.4f}{b.rp:11.4f}{a.rp:11.4f}")
    click.echo(f"  before: joints from the {STAGES[BEFORE]}; after: from the {STAGES[AFTER]}")
    if folder is not None:
        click.echo(f"report: {folder}/index.html")
