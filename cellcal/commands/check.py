"""``cellcal check``: is the calibration still good? A check campaign — ``cellcal run
--kind check`` under its own name: the same runner, the same stored campaign and
progress on stderr, its verdict printed. Exit 4 when the robot is out of its limits
(recalibrate); a warning exits 0."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import click

from cellcal.campaign.check_kind import MODEL, POSES
from cellcal.commands.output import SEED, TIME_SCALE, print_json
from cellcal.commands.run import CampaignRun, option_type, run_kind

if TYPE_CHECKING:
    from cellcal.campaign.runner import CampaignOutcome

#: the check ran and the robot is out of its limits: recalibrate
EXIT_RECALIBRATE = 4


@click.command("check")
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option("--mock", is_flag=True, help="Run against the twins of the simulated cell.")
@click.option("--db", "db_path", help="Database (default: storage.database of the config).")
@click.option(
    "--model",
    "model_spec",
    help="Check this calibrated model (default: the database's current model).",
)
@click.option(
    "--poses", type=option_type(POSES), help="Poses to measure (default: [check] poses, 12)."
)
@click.option("--seed", type=SEED, help="Mock mode: the simulated truth's and noise's seed.")
@click.option("--time-scale", type=TIME_SCALE, help="Mock mode: wall seconds per simulated second.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def check(
    config_path: str | None,
    mock: bool,
    db_path: str | None,
    model_spec: str | None,
    poses: int | None,
    seed: int | None,
    time_scale: float | None,
    as_json: bool,
) -> None:
    """Check the robot against its current model between calibrations: a few poses
    measured like a calibration's, their errors against limits from the model's own
    uncertainty and earlier checks, a verdict (ok, warning, recalibrate) and its likely
    cause. Exit 4: recalibrate. A check never writes a model."""
    run_kind(
        CampaignRun(
            kind="check",
            given={MODEL.name: model_spec, POSES.name: poses},
            config_path=config_path,
            mock=mock,
            db_path=db_path,
            seed=seed,
            time_scale=time_scale,
            as_json=as_json,
        )
    )


def print_check(out: CampaignOutcome, folder: str | None, as_json: bool) -> None:
    """A check's verdict: its JSON, or its lines; exit 4 on ``recalibrate``."""
    from cellcal.calib.drift import MIN_EARLIER, RECALIBRATE
    from cellcal.campaign.check_kind import CheckOutcome

    c = out.result
    assert isinstance(c, CheckOutcome)
    if as_json:
        doc = c.to_dict()
        print_json(doc if folder is None else {**doc, "report": folder})
    else:
        lim = c.limits
        click.echo(
            f"check (campaign {c.campaign_id} in {c.db_path}) of {c.model}, digest "
            f"{c.model_digest}: {len(c.errors_mm)} poses measured by {c.reference_sensor}"
        )
        click.echo(
            f"  error RMS {c.rms_mm:.4f} mm, max {c.max_mm:.4f} mm; limits: warning "
            f"{lim.warning_mm:.4f}, recalibrate {lim.limit_mm:.4f} mm"
        )
        checks = f"{lim.n_earlier} earlier ok check{'s' if lim.n_earlier != 1 else ''}"
        earlier = (
            f"{checks} {lim.earlier_mm:.4f} mm"
            if lim.earlier_mm is not None
            else f"{checks} ({MIN_EARLIER} are needed to count)"
        )
        held = "—" if lim.validation_mm is None else f"{lim.validation_mm:.4f} mm"
        click.echo(
            f"  1σ RMS: the model predicts {lim.predicted_mm:.4f} mm; its validation "
            f"measured {held}; {earlier}"
        )
        click.echo(f"verdict: {c.verdict}")
        if c.verdict != "ok":
            click.echo(f"  cause: {c.cause or 'no single cause explains the errors'}")
        if folder is not None:
            click.echo(f"report: {folder}/index.html")
    if c.verdict == RECALIBRATE:
        sys.exit(EXIT_RECALIBRATE)
