"""Each campaign kind declares its command-line options once (``KindOption``, in its kind
module), and ``cellcal run`` and ``cellcal campaign start`` make ``--kind`` and those
options from the table of kinds (issue 30): a new kind's options come with it, with
their help, type and bounds, and a command line that gives an option of another kind is
refused in one line. The commands themselves take exactly the table's options."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import click
import pytest
from click.testing import CliRunner

from cellcal.campaign.kinds import Acquired, Analysis, CampaignKind, KindOption, all_kinds
from cellcal.commands.campaign import start
from cellcal.commands.run import kind_options, run
from cellcal.errors import InputError


@dataclass(frozen=True)
class DriftKind:
    """A kind that is not (yet) cellcal's: a drift check, with an option of its own and
    one it shares with the ISO 9283 test."""

    name: str = "drift"
    title: str = "drift check"
    command_options: tuple[KindOption, ...] = (
        KindOption("hours", "hours between checks.", low=1, high=72, default=8),
        KindOption("cycles", "cycles per check.", low=2, high=1000, default=5),
    )

    def options(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        return dict(raw)

    def read_options(self, given: Mapping[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in given.items() if v is not None}

    def plan(self, config: Any, options: Mapping[str, Any]) -> Any:
        raise AssertionError("this test reads the kind's options only; it plans nothing")

    def created(self, options: Mapping[str, Any]) -> Sequence[tuple[str, str]]:
        return ()

    def analyse(self, done: Acquired) -> Analysis:
        raise AssertionError("this test reads the kind's options only; it analyses nothing")


def _command(kinds: Mapping[str, CampaignKind], sent: bool = False) -> click.Command:
    @click.command()
    @kind_options(kinds, sent=sent)
    def command(kind: str, **given: Any) -> None:
        click.echo(f"{kind} {sorted(given.items())}")

    return command


def test_a_new_kinds_options_come_from_the_table() -> None:
    kinds: dict[str, CampaignKind] = {**all_kinds(), "drift": DriftKind()}
    command = _command(kinds)
    names = [p.name for p in command.params]
    assert names == ["kind", "model", "poses", "cycles", "hours"]
    help_ = {p.name: p.help for p in command.params if isinstance(p, click.Option)}
    assert help_["kind"] == (
        "The campaign's kind: calibration, check (the check: --model, --poses), iso9283 "
        "(the ISO 9283 test: --model, --cycles), or drift (the drift check: --hours, "
        "--cycles)."
    )
    assert help_["hours"] == "--kind drift: hours between checks."
    assert help_["cycles"] == "--kind iso9283, drift: cycles (the standard: 30)."
    runner = CliRunner()
    result = runner.invoke(command, ["--kind", "drift", "--hours", "12"])
    assert result.exit_code == 0, result.output
    assert result.output == (
        "drift [('cycles', None), ('hours', 12), ('model', None), ('poses', None)]\n"
    )
    result = runner.invoke(command, ["--hours", "73"])
    assert result.exit_code == 2 and "1<=x<=72" in result.output
    # An option of another kind is refused by the kind asked for, in one line.
    with pytest.raises(InputError, match=r"takes no option --hours .*for another --kind"):
        all_kinds()["iso9283"].read_options({"model": "m.toml", "hours": 12})
    with pytest.raises(InputError, match=r"a calibration takes no options \(hours given\)"):
        all_kinds()["calibration"].read_options({"hours": 12, "model": None})


@pytest.mark.parametrize(("command", "sent"), [(run, False), (start, True)])
def test_run_and_campaign_start_take_the_tables_options(command: click.Command, sent: bool) -> None:
    """The real commands: every kind's options, with the help the kind gives them (in
    ``campaign start``, the one that says what is sent), after ``--kind``."""
    # an option two kinds declare is one option, with the first one's help
    declared: dict[str, tuple[KindOption, list[str]]] = {}
    for k in all_kinds().values():
        for o in k.command_options:
            declared.setdefault(o.name, (o, []))[1].append(k.name)
    params = {p.name: p for p in command.params if isinstance(p, click.Option)}
    names = [p.name for p in command.params]
    at = names.index("kind")
    assert names[at + 1 : at + 1 + len(declared)] == list(declared)
    for o, kinds in declared.values():
        text = o.sent if sent and o.sent else o.help
        assert params[o.name].help == f"--kind {', '.join(kinds)}: {text}"
    assert params["model"].help == (
        "--kind check, iso9283: the calibrated model (its text is sent)."
        if sent
        else "--kind check, iso9283: the calibrated model (model.toml)."
    )
    cycles = params["cycles"].type
    assert isinstance(cycles, click.IntRange) and (cycles.min, cycles.max) == (2, 1000)
