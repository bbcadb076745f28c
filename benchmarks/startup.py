"""Start-up benchmark: how long `cellcal --version`, `cellcal --help` and a subcommand's
`--help` take, against a bare click program with one command (the peer), in one run.

Each command is run ``--runs`` times in a fresh interpreter, in turn with the peer, and
the median wall time kept; then `python -X importtime` says which imports the slowest
of cellcal's cost most (cumulative microseconds). Goal (issue 28): `--version` and
`--help` under 0.3 s.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

PEER = (
    "import click\n"
    "@click.group()\n@click.version_option('1', '--version')\ndef cli():\n    'A peer.'\n"
    "@cli.command()\ndef hello():\n    'Say hello.'\n"
    "cli(prog_name='peer')\n"
)


def timed(args: list[str], runs: int) -> float:
    """Median wall time (s) of ``args`` run ``runs`` times."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(args, capture_output=True, check=False)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def heaviest_imports(args: list[str], n: int = 5) -> list[tuple[int, str]]:
    """The ``n`` top-level imports with the largest cumulative time (µs)."""
    err = subprocess.run(
        [sys.executable, "-X", "importtime", *args], capture_output=True, text=True
    ).stderr
    rows = []
    for line in err.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[1].strip().isdigit():
            name = parts[2].rstrip()
            if not name.startswith("  "):  # top level of its chain
                rows.append((int(parts[1]), name.strip()))
    return sorted(rows, reverse=True)[:n]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    cellcal = [sys.executable, "-m", "cellcal"]
    peer = [sys.executable, "-c", PEER]
    cases = [
        ("--version", [*cellcal, "--version"], [*peer, "--version"]),
        ("--help", [*cellcal, "--help"], [*peer, "--help"]),
        ("models --help", [*cellcal, "models", "--help"], [*peer, "hello", "--help"]),
        ("rig --help", [*cellcal, "rig", "--help"], [*peer, "hello", "--help"]),
    ]
    print(f"start-up, median of {args.runs} runs each, a fresh interpreter every run:")
    for label, ours, theirs in cases:
        a, b = timed(ours, args.runs), timed(theirs, args.runs)
        goal = " (goal < 0.3 s)" if label in ("--version", "--help") else ""
        print(f"  cellcal {label:14s} {a:.3f} s{goal}; bare click peer {b:.3f} s -> {a / b:.2f}x")
    print("  heaviest imports of `cellcal rig --help` (cumulative):")
    for us, name in heaviest_imports(["-m", "cellcal", "rig", "--help"]):
        print(f"    {us / 1e6:.3f} s  {name}")


if __name__ == "__main__":
    main()
