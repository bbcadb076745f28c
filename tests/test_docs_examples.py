"""Every example in README.md and docs/ runs literally.

Convention of the documents: a ```sh block holds commands that are run, line by line,
and must succeed (exit 0); a ```console block is a transcript: its ``$ `` lines are run
and a ``cellcal: refused: …`` (exit 3) or ``cellcal: error: …`` (exit 2) line shown under
a command must be exactly what it prints, as must a check's ``verdict: recalibrate`` (exit
4, on stdout). ```text blocks (commands for real devices, a
server that runs until stopped, configuration messages) are not run.

Each document runs in its own scratch folder that sees the repository's ``cellcal`` and
``tests`` folders and a copy of ``config`` and ``examples``, so relative paths work as
they do in a checkout, and whatever the examples write stays out of the checkout (the
test checks that they wrote nothing into it). ``make`` lines are
the set-up itself and are skipped; ``.venv/bin/cellcal`` and ``cellcal`` run this
interpreter's cellcal: a line that is one command reading and writing files alone
(:data:`IN_PROCESS`: calibrate, predict, report, …) through its entry point in the test's
own process, in the document's folder and environment; any other line in bash.

A few commands appear, word for word, in more than one document, and read nothing but
the checkout (:data:`SHARED`): the session runs each once, and a document that comes to
it later is handed what that run printed, its exit code and the files it wrote (across
the parallel run's workers, in the session's shared temporary folder), and checks them
as its own.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.bundled_campaign import producing, shared_folder
from tests.inprocess import cellcal

pytestmark = [pytest.mark.twin, pytest.mark.slow]

ROOT = Path(__file__).parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINKED = ("cellcal", "tests")  # read only: the paths the examples name (cellcal/data, tests/data)
COPIED = ("config", "examples")  # a relative database path in a config lands beside it
#: README's main example, the bundled campaign: its database is handed to the tests that
#: read such a campaign (tests/bundled_campaign.py)
BUNDLED_RUN = re.compile(r"^(\.venv/bin/)?cellcal run --mock\s*(#.*)?$")
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
#: Commands (their words, without a comment) that several documents run, whose every
#: input is in the checkout (config, examples, tests/data, the bundled cell) save the
#: files they write: the tracker cell's campaigns (README, compensation.md, iso9283.md;
#: campaign.md, database.md, checks.md), the rig's capture and calibration (README,
#: photogrammetry.md) and the few that only print (README and planning.md, urdf.md,
#: calibration.md, acceptance.md, paper-errata.md). Run once per session; a
#: document in whose folder one of the files that run wrote already exists runs it
#: itself.
SHARED = frozenset(
    {
        "cellcal run --mock --config config/mock-cell-tracker.toml --db demo.db --report report",
        "cellcal run --mock --config config/mock-cell-tracker.toml --db doc.db",
        "cellcal plan --mock --optimal 24 --criterion I",
        "cellcal predict --model tests/data/urdf/ur5_robot.urdf --joints examples/ur5-joints.csv",
        "cellcal models",
        "cellcal calibrate --model kuka-kr5-arc --data examples/metres.csv --out robot.toml",
        "cellcal register --src cellcal/data/paper_table4_station1.csv --dst "
        "cellcal/data/paper_table4_station2.csv --method line --line-a P1,P2 --line-b P2,P3",
        # README and photogrammetry.md: the rig from rendered views (the calibration reads
        # the views the capture wrote, handed over with it)
        "cellcal rig capture --mock --board config/mock-board.toml --sets 12 --out views",
        "cellcal rig calibrate --board config/mock-board.toml --views views --out my-rig.toml",
    }
)
#: A check's verdict that exits 4, shown under the command in a transcript.
RECALIBRATE = "verdict: recalibrate"
#: How long a document waits for another worker's run of a shared command, s.
SHARED_WAIT_S = 600.0


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
                    if after.startswith(("cellcal: refused: ", "cellcal: error: ", RECALIBRATE)):
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
    # -P: cellcal is imported from where it is installed (the checkout, as for a user
    # there), not through the link beside the examples; through the link every document
    # compiled it again into the cache of compiled modules, under a new path each run
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" -P -m cellcal "$@"\n')
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
    shared = shared_folder(tmp_path_factory) / "doc-steps"
    with producing(tmp_path_factory) if doc.name == "README.md" else nullcontext() as publish:
        for step in todo:
            _run(step, tmp_path, env, shared)
            if publish is not None and BUNDLED_RUN.match(step.command):
                publish(tmp_path / ".data" / "cellcal" / "cellcal.db")
    assert _untracked() == before, "an example wrote into the checkout"


def _run(step: Step, tmp_path: Path, env: dict[str, str], shared: Path) -> None:
    """One step, run as the document shows it (or its shared run handed over, see
    :data:`SHARED`); what it must say, said."""
    command = step.command.replace(".venv/bin/cellcal", "cellcal")
    key = " ".join(shlex.split(command, comments=True))
    if key not in SHARED:
        _check(step, _execute(command, tmp_path, env))
        return
    with _shared_run(shared / hashlib.sha256(key.encode()).hexdigest()[:16], tmp_path) as run:
        res = run.result or _execute(command, tmp_path, env)
        _check(step, res)
        run.keep(res)


#: Commands that only read and write files (no device, twin, service or camera), run in
#: the test's own process (tests/inprocess.py) when the line is that command alone: the
#: same entry point and arguments, in the document's folder, with its environment, without
#: a second interpreter's start and imports each time (about 0.5 s of CPU a command)
IN_PROCESS = frozenset(
    {"calibrate", "predict", "register", "models", "export", "compensate", "report", "campaign"}
)
#: What makes a line more than one command for the shell (pipes, redirections, variables,
#: globs, lists): such a line runs in bash
SHELL_SYNTAX = re.compile(r"[|&;<>$`*?\[\]~(){}\\]")


def _in_process(command: str) -> list[str] | None:
    """The arguments of a line that is one ``cellcal`` command of :data:`IN_PROCESS`
    without ``--mock`` (``campaign`` only as ``campaign list --db``), else None."""
    words = shlex.split(command, comments=True)
    plain = " ".join(words)
    if len(words) < 2 or words[0] != "cellcal" or SHELL_SYNTAX.search(plain):
        return None
    args = words[1:]
    if args[0] not in IN_PROCESS or "--mock" in args:
        return None
    if args[0] == "campaign" and (args[1:2] != ["list"] or "--db" not in args):
        return None
    return args


def _execute(command: str, tmp_path: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    args = _in_process(command)
    if args is not None:
        saved, cwd = dict(os.environ), Path.cwd()
        os.environ.clear()
        os.environ.update(env)
        os.chdir(tmp_path)
        try:
            return cellcal(*args)
        finally:
            os.chdir(cwd)
            os.environ.clear()
            os.environ.update(saved)
    return subprocess.run(
        ["bash", "-c", command],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def _check(step: Step, res: subprocess.CompletedProcess[str]) -> None:
    said = res.stderr.strip().splitlines()
    if not step.expect:
        assert res.returncode == 0, f"{step.where}: {step.command}\n{res.stderr[-2000:]}"
        return
    first = step.expect[0]
    code = 3 if first.startswith("cellcal: refused") else 4 if first == RECALIBRATE else 2
    assert res.returncode == code, f"{step.where}: {step.command}\n{res.stderr[-2000:]}"
    if code == 4:
        said = res.stdout.strip().splitlines()
    for line in step.expect:
        assert line in said, f"{step.where}: {step.command}\nshown: {line}\nsaid: {said}"


class _SharedRun:
    """A shared command's one run in the session (``folder``): what it printed and the
    files it wrote, handed to ``tmp_path`` (``result``), or kept once checked (``keep``)."""

    def __init__(self, folder: Path, tmp_path: Path, owned: bool) -> None:
        self.folder, self.tmp_path, self.owned = folder, tmp_path, owned
        self.result: subprocess.CompletedProcess[str] | None = None
        self.before: tuple[dict[str, tuple[int, int]], set[str]] = ({}, set())
        record = folder / "record.json"
        if owned and record.exists():
            kept = json.loads(record.read_text())
            if not any((tmp_path / name).exists() for name in kept["files"]):
                for name in kept["dirs"]:
                    (tmp_path / name).mkdir(parents=True, exist_ok=True)
                for name in kept["files"]:
                    shutil.copyfile(folder / "files" / name, tmp_path / name)
                self.result = subprocess.CompletedProcess(
                    kept["args"], kept["returncode"], kept["stdout"], kept["stderr"]
                )
                return
        self.before = _listing(tmp_path)

    def keep(self, res: subprocess.CompletedProcess[str]) -> None:
        if not self.owned or self.result is not None or (self.folder / "record.json").exists():
            return
        files, dirs = _listing(self.tmp_path)
        written = sorted(name for name, seen in files.items() if self.before[0].get(name) != seen)
        if any(name in self.before[0] for name in written):
            return  # it changed a file it found: not its own output alone, not handed on
        for name in written:
            (self.folder / "files" / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(self.tmp_path / name, self.folder / "files" / name)
        kept = {
            "args": res.args,
            "returncode": res.returncode,
            "stdout": res.stdout,
            "stderr": res.stderr,
            "files": written,
            "dirs": sorted(dirs - self.before[1]),
        }
        part = self.folder / "record.json.part"
        part.write_text(json.dumps(kept))
        part.rename(self.folder / "record.json")


@contextmanager
def _shared_run(folder: Path, tmp_path: Path) -> Iterator[_SharedRun]:
    """The shared command's folder held by this test while it copies or runs it (another
    worker's test waits up to :data:`SHARED_WAIT_S`, then runs it without sharing)."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "lock", "a") as lock:
        deadline = time.monotonic() + SHARED_WAIT_S
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                owned = True
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    owned = False
                    break
                time.sleep(0.05)
        try:
            yield _SharedRun(folder, tmp_path, owned)
        finally:
            if owned:
                fcntl.flock(lock, fcntl.LOCK_UN)


def _listing(folder: Path) -> tuple[dict[str, tuple[int, int]], set[str]]:
    """The document's folder (not the linked checkout): each file's size and time, and
    the folders, by relative path."""
    files: dict[str, tuple[int, int]] = {}
    dirs: set[str] = set()
    for top, subdirs, names in os.walk(folder):
        subdirs[:] = [d for d in subdirs if not Path(top, d).is_symlink()]
        rel = Path(top).relative_to(folder)
        dirs.update(str(rel / d) for d in subdirs)
        for name in names:
            path = Path(top, name)
            if not path.is_symlink():
                st = path.stat()
                files[str(rel / name)] = (st.st_size, st.st_mtime_ns)
    return files, dirs


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
