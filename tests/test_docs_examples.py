"""Every example in README.md and docs/ runs literally.

Convention of the documents: a ```sh block holds commands that are run, line by line,
and must succeed (exit 0); a ```console block is a transcript: its ``$ `` lines are run
and a ``cellcal: refused: …`` (exit 3) or ``cellcal: error: …`` (exit 2) line shown under
a command must be exactly what it prints. ```text blocks (commands for real devices, a
server that runs until stopped, configuration messages) are not run.

Each document runs in its own scratch folder that sees the repository's ``cellcal`` and
``tests`` folders and a copy of ``config`` and ``examples``, so relative paths work as
they do in a checkout, and whatever the examples write stays out of the checkout (the
test checks that they wrote nothing into it). ``make`` lines are
the set-up itself and are skipped; ``.venv/bin/cellcal`` and ``cellcal`` run this
interpreter's cellcal.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.bundled_campaign import producing

pytestmark = [pytest.mark.twin, pytest.mark.slow]

ROOT = Path(__file__).parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINKED = ("cellcal", "tests")  # read only
COPIED = ("config", "examples")  # a relative database path in a config lands beside it
#: README's main example, the bundled campaign: its database is handed to the tests that
#: read such a campaign (tests/bundled_campaign.py)
BUNDLED_RUN = re.compile(r"^(\.venv/bin/)?cellcal run --mock\s*(#.*)?$")
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


@dataclass(frozen=True)
class Step:
    where: str
    command: str
    expect: tuple[str, ...]  # refusal / error lines shown under a console command


def _logical_lines(body: str) -> list[str]:
    """Lines with backslash continuations joined."""
    out: list[str] = []
    pending = ""
    for line in body.splitlines():
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        out.append(pending + line)
        pending = ""
    return out


def steps(doc: Path) -> list[Step]:
    text = doc.read_text(encoding="utf-8")
    out: list[Step] = []
    for m in BLOCK.finditer(text):
        lang, body = m.group(1), m.group(2)
        where = f"{doc.relative_to(ROOT)}:{text[: m.start()].count(chr(10)) + 1}"
        if lang == "sh":
            for line in _logical_lines(body):
                cmd = line.strip()
                if cmd and not cmd.startswith("#") and not cmd.startswith("make "):
                    out.append(Step(where, cmd, ()))
        elif lang == "console":
            lines = _logical_lines(body)
            for k, line in enumerate(lines):
                if not line.startswith("$ "):
                    continue
                shown = []
                for after in lines[k + 1 :]:
                    if after.startswith("$ "):
                        break
                    if after.startswith(("cellcal: refused: ", "cellcal: error: ")):
                        shown.append(after)
                out.append(Step(where, line[2:].strip(), tuple(shown)))
    return out


def _scratch(tmp_path: Path) -> Path:
    for name in LINKED:
        (tmp_path / name).symlink_to(ROOT / name)
    for name in COPIED:
        shutil.copytree(ROOT / name, tmp_path / name)
    shim = tmp_path / ".bin"
    shim.mkdir()
    exe = shim / "cellcal"
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m cellcal "$@"\n')
    exe.chmod(0o755)
    return shim


def test_every_document_has_examples_that_are_collected() -> None:
    assert steps(ROOT / "README.md"), "README.md: no runnable example found"


@pytest.mark.parametrize("doc", DOCUMENTS, ids=lambda p: p.name)
@pytest.mark.timeout(1500)  # README runs the bundled campaign with its camera rig: minutes
def test_examples_run_literally(
    doc: Path, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    todo = steps(doc)
    if not todo:
        pytest.skip(f"{doc.name}: no runnable examples")
    before = _untracked()
    shim = _scratch(tmp_path)
    env = {**os.environ, "PATH": f"{shim}:{os.environ.get('PATH', '')}"}
    env.pop("CELLCAL_SOCKET", None)
    env.pop("STATE_DIRECTORY", None)
    env["XDG_DATA_HOME"] = str(tmp_path / ".data")  # the default database's folder
    with producing(tmp_path_factory) if doc.name == "README.md" else nullcontext() as publish:
        for step in todo:
            _run(step, tmp_path, env)
            if publish is not None and BUNDLED_RUN.match(step.command):
                publish(tmp_path / ".data" / "cellcal" / "cellcal.db")
    assert _untracked() == before, "an example wrote into the checkout"


def _run(step: Step, tmp_path: Path, env: dict[str, str]) -> None:
    """One step, run as the document shows it; what it must say, said."""
    command = step.command.replace(".venv/bin/cellcal", "cellcal")
    res = subprocess.run(
        ["bash", "-c", command],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    said = res.stderr.strip().splitlines()
    if not step.expect:
        assert res.returncode == 0, f"{step.where}: {step.command}\n{res.stderr[-2000:]}"
        return
    code = 3 if step.expect[0].startswith("cellcal: refused") else 2
    assert res.returncode == code, f"{step.where}: {step.command}\n{res.stderr[-2000:]}"
    for line in step.expect:
        assert line in said, f"{step.where}: {step.command}\nshown: {line}\nsaid: {said}"


def _untracked() -> set[str]:
    """Files in the checkout's config folder that git does not track (ignored ones
    included); nothing to compare without git."""
    if shutil.which("git") is None:
        return set()
    res = subprocess.run(
        ["git", "status", "--porcelain", "--ignored", "--untracked-files=all", "--", "config"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    return set(res.stdout.splitlines())
