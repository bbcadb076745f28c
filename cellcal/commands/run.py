"""``cellcal run``: a whole campaign, or ``--resume ID`` of an interrupted one.

Its first line comes within a second: the campaign's modules (the analysis, scipy, the
report's matplotlib) are loaded after it. Its progress lines: ``progress.py``."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, TypeVar

import click

from cellcal.campaign.kinds import DEFAULT_KIND, CampaignKind, KindOption, all_kinds, kind_named
from cellcal.campaign.stop_request import StopRequest
from cellcal.commands.output import SEED, TIME_SCALE, print_json
from cellcal.commands.progress import BarProgress, LineProgress
from cellcal.commands.terms_output import repeats_text
from cellcal.config import CellConfig, default_database, load_config
from cellcal.errors import InputError
from cellcal.extras import require
from cellcal.store.connection import database_path

if TYPE_CHECKING:
    from cellcal.calib.calibration_result import CalibrationResult
    from cellcal.campaign.records import Subscriber
    from cellcal.campaign.runner import CampaignOutcome

EXIT_INTERRUPTED = 130


def bundled_mock_cell() -> tuple[CellConfig, str]:
    ref = resources.files("cellcal") / "data" / "mock-cell.toml"
    with resources.as_file(ref) as p:
        return load_config(p, relative_paths=False), "bundled config/mock-cell.toml"


def cell_config(config_path: str | None, mock: bool) -> tuple[CellConfig, str]:
    """The configuration a command runs with, and where it came from: ``--config``, or
    with ``--mock`` alone the bundled simulated cell."""
    if config_path is not None:
        return load_config(config_path), config_path
    if mock:
        return bundled_mock_cell()
    raise InputError("give --config FILE, or --mock for the bundled simulated cell")


def _corrections(c: CalibrationResult) -> str:
    """The largest identified kinematic correction of each unit, with its uncertainty."""
    parts = []
    for unit, digits in (("mm", 3), ("deg", 4)):
        found = [
            p for p in c.parameters if p.identified and p.kind != "target_offset" and p.unit == unit
        ]
        if found:
            top = max(found, key=lambda p: abs(p.value))
            sign = "°" if unit == "deg" else " mm"
            parts.append(
                f"{len(found)} {'angles' if unit == 'deg' else 'lengths'}, largest {top.name} "
                f"{top.value:+.{digits}f} ± {top.std:.{digits}f}{sign}"
            )
    return "; ".join(parts) or "none"


def _xyz(v: Any, digits: int) -> str:
    return "(" + ", ".join(f"{float(x):.{digits}f}" for x in v) + ")"


def _print_summary(out: CampaignOutcome, folder: str | None, residuals: bool) -> None:
    """What was measured, the headline figures with their uncertainty, the validation
    before and after, warnings, where the details are; every pose's residual only with
    ``residuals`` (always in the report and in --json)."""
    import numpy as np

    from cellcal.campaign.analysis import PAPER, CampaignSummary
    from cellcal.commands.calibrate import at_nominal_text, echo_points

    s: CampaignSummary | None = out.summary
    plan = out.plan
    sensors = ", ".join(x.name for x in out.config.sensor)
    click.echo(
        f"{out.config.name}: campaign {out.campaign_id} complete: {len(plan.poses)} poses ("
        f"{plan.count('calibration')} calibration, {plan.count('validation')} validation), "
        f"{out.config.campaign.samples_per_pose} samples per pose from {sensors}"
    )
    if plan.unreachable:
        regions = sorted({u.region for u in plan.unreachable})
        click.echo(
            f"unreachable, not measured: {len(plan.unreachable)} poses (in {', '.join(regions)})"
        )
    if s is None:
        return
    c = s.calibration
    agree = {a.sensor: a for a in s.agreements}
    click.echo(
        "registration to the robot base, RMS at the calibration poses, nominal → calibrated:"
    )
    for r in s.registrations:
        if r.sensor == s.reference:
            rot = float(np.degrees(np.max(c.frame_std[:3])))
            frame = f"± {np.max(c.frame_std[3:]):.3f} mm, ± {rot:.4f}° (1σ)"
            note = f"the reference; its frame {frame}"
        elif r.sensor in agree:
            a = agree[r.sensor]
            note = f"against {s.reference} {a.rms_mm:.4f} mm RMS, χ²/dof {a.chi2_per_dof:.2f}"
        else:
            note = ""
        click.echo(
            f"  {r.sensor:<10}{r.rms_nominal_mm:8.4f} → {r.rms_calibrated_mm:.4f} mm"
            f"  ({r.n} poses{'; ' + note if note else ''})"
        )
    click.echo(
        f"calibration from {s.reference}: {len(c.identified)} of {len(c.parameters)} "
        f"parameters of the robot and target offset identified (the sensor frame besides), "
        f"σ0 {c.sigma0:.2f}, condition number {c.condition_number:.3g} "
        f"({c.condition_number_equal_weights:.4g} with equal weights, `plan`'s measure, at the "
        "poses as measured)"
    )
    click.echo(f"  corrections: {_corrections(c)}")
    click.echo(f"  target offset {_xyz(c.target_offset, 3)} ± {_xyz(c.target_offset_std, 3)} mm")
    click.echo(f"  left at nominal: {at_nominal_text(c)}")
    outside = ", ".join(r.region for r in s.regions if r.region != "cube") or "none"
    click.echo(
        f"validation ({s.reference}; outside: {outside}), RMS / max, "
        "before → after calibration, mm:"
    )
    for label, region in (("inside the cube", s.inside), ("outside the cube", s.outside)):
        if region is not None:
            b, f = region.before, region.after
            click.echo(
                f"  {label:<17}{f'({b.n} poses)':<12}{b.rms:.4f} / {b.max:.4f} → "
                f"{f.rms:.4f} / {f.max:.4f}"
            )
    click.echo(
        f"  all {s.n_validation} poses: RMS {s.validation_before.rms:.4f} → "
        f"{s.validation_after.rms:.4f} mm, {s.improvement_pct:.1f} % reduction"
    )
    if s.spread is not None:
        click.echo(
            f"  another campaign would give {s.spread.low:.4f}–{s.spread.high:.4f} mm after "
            f"(90 % of {s.spread.draws} repeats drawn from the fit's covariance and the "
            "poses' noise)"
        )
    if s.repeats:
        click.echo(f"reference poses ({s.reference}): " + repeats_text(s.repeats))
    click.echo(
        f"the paper, after calibration: {PAPER['cl_inside_mm']:.3f} mm in the calibrated region "
        f"({PAPER['other_method_mm']:.3f} mm with another registration method), "
        f"{PAPER['cl_outside_mm']:.3f} mm outside it"
    )
    for w in (*c.warnings, *s.warnings):
        click.echo(f"warning: {w}")
    outliers = [f"{p.name} (z {p.z:.1f})" for p in s.points if p.outlier]
    flagged = f"outliers: pose {', '.join(outliers)}" if outliers else "no outlier"
    click.echo(
        f"{s.reference} residual at the {len(s.points)} calibration poses: RMS "
        f"{c.rms_after:.4f} mm, max {c.max_after:.4f} mm; {flagged}"
        + ("" if residuals else " (each pose: --residuals, or the report)")
    )
    if residuals:
        echo_points(s.points, f"{s.reference} at the calibration poses (by plan index)")
    click.echo(f"database: {out.db_path} (campaign {out.campaign_id})")
    if folder is not None:
        click.echo(f"report: {Path(folder) / 'index.html'}")
    else:
        where = f"--db {out.db_path} --campaign {out.campaign_id}"
        click.echo(f"the report, every figure: cellcal report {where} --out DIR")


F = TypeVar("F", bound=Callable[..., Any])


def _listed(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + ", or " + names[-1]


def option_type(o: KindOption) -> click.IntRange | None:
    """A kind's option's type on the command line (None: a text)."""
    return None if o.low is None or o.high is None else click.IntRange(o.low, o.high)


def kind_options(
    kinds: Mapping[str, CampaignKind] | None = None, *, sent: bool = False
) -> Callable[[F], F]:
    """``--kind`` and every kind's own options (``KindOption``), as ``cellcal run`` and
    (``sent``: the values go to the service) ``cellcal campaign start`` take them: from
    the table of kinds (``kinds.all_kinds``), so that a new kind's options come with it.
    The command is given each option by its name, None where it is not given. An option
    two kinds declare is one option (the first's type), for either ``--kind``."""
    table = all_kinds() if kinds is None else kinds
    declared: dict[str, tuple[KindOption, list[str]]] = {}
    for k in table.values():
        for o in k.command_options:
            declared.setdefault(o.name, (o, []))[1].append(k.name)
    each = [
        f"{name} (the {k.title}: {', '.join('--' + o.name for o in k.command_options)})"
        if k.command_options
        else name
        for name, k in table.items()
    ]

    def add(f: F) -> F:
        # a decorator's option shows above those added before it: the last one first
        for o, names in reversed(declared.values()):
            text = o.sent if sent and o.sent else o.help
            help_ = f"--kind {', '.join(names)}: {text}"
            f = click.option(f"--{o.name}", o.name, type=option_type(o), help=help_)(f)
        return click.option(
            "--kind",
            default=DEFAULT_KIND,
            show_default=True,
            help=f"The campaign's kind: {_listed(each)}.",
        )(f)

    return add


def given_options(params: dict[str, Any]) -> dict[str, Any]:
    """The kinds' options out of a command's parameters (taken out of ``params``)."""
    names = {o.name for k in all_kinds().values() for o in k.command_options}
    return {name: params.pop(name) for name in list(params) if name in names}


def other_kind_asked(kind: str, given: Mapping[str, Any]) -> bool:
    """Whether a command line asks for a kind other than the default, or gives options."""
    return kind != DEFAULT_KIND or any(v is not None for v in given.values())


@dataclass(frozen=True)
class CampaignRun:
    """What ``cellcal run`` (and ``cellcal iso9283``) asks for: a campaign of ``kind``
    started (``given``: its options as the command line has them, None where not given)
    or resumed (``resume_id``), its progress on stderr and its outcome printed as its
    kind's."""

    kind: str = DEFAULT_KIND
    given: Mapping[str, Any] = field(default_factory=dict)
    config_path: str | None = None
    mock: bool = False
    db_path: str | None = None
    seed: int | None = None
    time_scale: float | None = None
    resume_id: int | None = None
    accept: bool = False
    report_dir: str | None = None
    residuals: bool = False
    as_json: bool = False


@click.command()
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option("--mock", is_flag=True, help="Simulated devices; without --config, the bundled cell.")
@click.option(
    "--db", "db_path", help="Campaign database (default: storage.database of the config)."
)
@click.option(
    "--seed", type=SEED, help="Mock mode: one seed for the simulated truth, noise and plan."
)
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    help="Mock mode: wall seconds per simulated second (0, the default: as fast as possible).",
)
@click.option(
    "--resume", "resume_id", type=int, help="Continue campaign ID from its last stored pose."
)
@click.option(
    "--accept",
    is_flag=True,
    help="Analyse and store the result even if an acceptance check fails (recorded).",
)
@click.option("--report", "report_dir", help="Write the campaign's report folder here at the end.")
@click.option(
    "--residuals",
    is_flag=True,
    help="Also list the reference sensor's residual at every calibration pose.",
)
@kind_options()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def run(**params: Any) -> None:
    """Run a whole campaign: plan, acquire, store, register, calibrate, validate, report.

    Every sample is stored before the analysis; a result that fails an acceptance check
    (the target does not follow the robot, units, implausible corrections) exits 3 and
    leaves the campaign stored with status "refused" (--resume ID --accept analyses it
    anyway). Ctrl-C or SIGTERM stops at the next safe point: the campaign is stored
    "interrupted", exit 130 with the command that resumes it. The text output is a
    summary; --residuals adds every calibration pose's residual (the report and --json
    have them). --kind iso9283 runs the ISO 9283 test instead (as `cellcal iso9283`);
    --resume goes on with a campaign of any kind."""
    given = given_options(params)
    asked = CampaignRun(given=given, **params)
    if asked.resume_id is not None and other_kind_asked(asked.kind, given):
        raise InputError("--resume takes the campaign's kind and options from the database")
    run_kind(asked)


def run_kind(a: CampaignRun) -> None:
    """A campaign started or resumed through the one runner (see :class:`CampaignRun`);
    its outcome printed as its kind's."""
    if a.report_dir is not None and Path(a.report_dir).exists() and not Path(a.report_dir).is_dir():
        raise InputError(f"--report {a.report_dir}: exists and is not a folder")
    if a.report_dir is not None:  # before the campaign, not after it
        require("cellcal run --report", "matplotlib")
    if a.db_path is not None:
        database_path(a.db_path)  # an empty path, :memory:, a URI: one line, before anything
        if not Path(a.db_path).resolve().parent.is_dir():
            raise InputError(f"--db {a.db_path}: folder {Path(a.db_path).parent} does not exist")
    stop = StopRequest()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        again = " again" if stop.is_set() else ""
        click.echo(f"cellcal: {name}{again}: finishing cleanly…", err=True)
        stop.request(name)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    progress: Subscriber = (
        BarProgress() if sys.stderr.isatty() and not a.as_json else LineProgress()
    )
    devices = "starting the devices' twins" if a.mock else "connecting the devices"
    try:
        if a.resume_id is not None:
            if a.config_path or a.mock or a.seed is not None:
                raise InputError(
                    "--resume takes only --db, --time-scale, --accept, --report, --residuals "
                    "and --json"
                )
            db = a.db_path if a.db_path is not None else default_database()
            if Path(db).is_file():  # else one line says so
                click.echo(f"resuming campaign {a.resume_id}: connecting the devices…", err=True)
            from cellcal.campaign.runner import resume_campaign

            outcome = resume_campaign(
                db,
                a.resume_id,
                time_scale=a.time_scale,
                stop=stop,
                subscribers=[progress],
                accept=a.accept,
            )
        else:
            options: dict[str, Any] = {}
            if other_kind_asked(a.kind, a.given):  # a file it names: read first
                options = kind_named(a.kind).read_options(a.given)
            config, source = cell_config(a.config_path, a.mock)
            if not a.mock and (a.seed is not None or a.time_scale is not None):
                raise InputError("--seed and --time-scale apply to mock mode (--mock)")
            db = a.db_path if a.db_path is not None else database_path(config.storage.database)
            from cellcal.campaign.runner import start_campaign

            def planning() -> None:
                click.echo(f"{config.name}: planning the poses and {devices}…", err=True)

            outcome = start_campaign(
                config,
                db,
                config_path=source,
                mock=a.mock,
                kind=a.kind,
                options=options,
                seed=a.seed,
                time_scale=a.time_scale or 0.0,
                stop=stop,
                subscribers=[progress],
                accept=a.accept,
                planning=planning,
            )
    finally:
        if isinstance(progress, BarProgress):
            progress.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if outcome.result is None and outcome.acquisition.awaiting_payload is not None:
        from cellcal.campaign.payloads import instruction

        click.echo(
            f"cellcal: campaign {outcome.campaign_id} paused with "
            f"{outcome.acquisition.stored} of {len(outcome.plan.poses)} poses stored: "
            f"{instruction(outcome.acquisition.awaiting_payload)}: cellcal run --resume "
            f"{outcome.campaign_id} --db {outcome.db_path}",
            err=True,
        )
        sys.exit(EXIT_INTERRUPTED)
    if outcome.result is None:
        why = f" ({stop.reason})" if stop.reason else ""
        click.echo(
            f"cellcal: campaign {outcome.campaign_id} interrupted{why} with "
            f"{outcome.acquisition.stored} of {len(outcome.plan.poses)} poses stored; "
            "resume with: cellcal run --resume "
            f"{outcome.campaign_id} --db {outcome.db_path}",
            err=True,
        )
        sys.exit(EXIT_INTERRUPTED)
    folder = None
    if a.report_dir is not None:
        click.echo(f"writing the report into {a.report_dir}…", err=True)
        from cellcal.reports.folder import write_report
        from cellcal.store.database import Store

        store = Store(outcome.db_path, readonly=True)
        try:
            folder = write_report(store, outcome.campaign_id, a.report_dir).folder
        finally:
            store.close()
    if outcome.summary is None:  # another kind's result: its own output
        if outcome.kind == "check":
            from cellcal.commands.check import print_check

            print_check(outcome, folder, a.as_json)
            return
        from cellcal.commands.iso9283 import print_outcome

        print_outcome(outcome, folder, a.as_json)
        return
    if a.as_json:
        s = outcome.summary
        doc: dict[str, Any] = {
            "campaign_id": outcome.campaign_id,
            "n_poses": len(outcome.plan.poses),
            "samples_per_pose": outcome.config.campaign.samples_per_pose,
            "sensors": [x.name for x in outcome.config.sensor],
            "rms_before_mm": s.validation_before.rms,
            "rms_after_mm": s.validation_after.rms,
            "improvement_pct": s.improvement_pct,
            "database": outcome.db_path,
            "unreachable": len(outcome.plan.unreachable),
            "clock_seconds": outcome.acquisition.clock_seconds,
            "report": folder,
            **{k: v for k, v in s.to_dict().items() if k not in ("campaign_id",)},
        }
        print_json(doc)
    else:
        _print_summary(outcome, folder, a.residuals)
