"""The bundled cell's whole campaign, tracker and camera rig, once per test session.

It is the suite's most expensive run (about 40 s of CPU: 128 poses, 20 sets of four
rendered 1280 × 1024 frames each over GigE Vision). README's main example runs it
literally (``cellcal run --mock``, in tests/test_docs_examples.py); the tests that check
what such a campaign leaves (tests/e2e/test_results.py, tests/e2e/test_report_page.py)
read that very database instead of running it again.

The hand-over, across the parallel run's workers (files in the session's shared
temporary folder):

* the README test *claims* the campaign when it starts (``bundled.claim``) and, once
  ``cellcal run --mock`` has exited 0, *publishes* a copy of its database
  (``bundled.db``, renamed into place); if it ends without that it writes
  ``bundled.failed``;
* a reader waits for what was claimed; where nothing is claimed — the README test is
  not in this session, or did not start within :data:`CLAIM_WAIT_S` — or the claim
  failed, it runs ``cellcal run --mock --db …`` itself: the same campaign, the same
  checks.

The README test is the session's first (tests/conftest.py orders it so), and a worker
runs its tests in the order they come, so no reader waits for a test queued behind it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

#: The README test's node id (the producer).
PRODUCER = "tests/test_docs_examples.py::test_examples_run_literally[README.md]"
#: How long a reader waits for the README test to claim the campaign, s: the workers
#: start their first tests together, once every worker has collected.
CLAIM_WAIT_S = 30.0
#: How long a reader waits for a claimed campaign, s.
RUN_WAIT_S = 1200.0


def shared_folder(factory: pytest.TempPathFactory) -> Path:
    """The folder every worker of this session sees (the workers' own temporary folders
    are beside each other in it)."""
    base = factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def producing(factory: pytest.TempPathFactory) -> Iterator[Callable[[Path], None]]:
    """For the README test: claim the campaign; the function given publishes a finished
    database; leaving without publishing says the claim failed."""
    shared = shared_folder(factory)
    (shared / "bundled.claim").touch()
    published: list[Path] = []

    def publish(db: Path) -> None:
        if published:
            return
        assert not Path(f"{db}-wal").exists(), "a finished database is one file"
        part = shared / "bundled.db.part"
        shutil.copyfile(db, part)
        part.rename(shared / "bundled.db")
        published.append(db)

    try:
        yield publish
    finally:
        if not published:
            (shared / "bundled.failed").touch()


def bundled_database(request: pytest.FixtureRequest, folder: Path) -> tuple[Path, bool]:
    """The bundled campaign's database copied to ``folder / 'c.db'``: the README test's
    when it ran (or runs) in this session, else one run here. Also whether it was run
    here (False: the README's)."""
    factory = request.getfixturevalue("tmp_path_factory")
    shared = shared_folder(factory)
    db = folder / "c.db"
    if (
        _readme_selected(request)
        and _wait(shared / "bundled.claim", CLAIM_WAIT_S, shared)
        and _wait(shared / "bundled.db", RUN_WAIT_S, shared)
    ):
        shutil.copyfile(shared / "bundled.db", db)
        return db, False
    res = subprocess.run(
        [sys.executable, "-m", "cellcal", "run", "--mock", "--db", str(db)],
        capture_output=True,
        text=True,
        timeout=RUN_WAIT_S,
        check=False,
    )
    assert res.returncode == 0, res.stderr
    return db, True


def _readme_selected(request: pytest.FixtureRequest) -> bool:
    return any(item.nodeid == PRODUCER for item in request.session.items)


def _wait(path: Path, timeout_s: float, shared: Path) -> bool:
    """Whether ``path`` appears within ``timeout_s`` (False at once once the claim has
    failed)."""
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if (shared / "bundled.failed").exists() or time.monotonic() > deadline:
            return False
        time.sleep(0.2)
    return True
