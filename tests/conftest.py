"""Shared fixtures: the paper's Table 4 points, a random rigid problem factory, and the
bundled simulated cell without its camera rig (campaigns in seconds, for the tests that
are not about the rig); and how the parallel run (`make unit`, `make check`) hands the
tests to its workers.

Markers (pyproject.toml): ``twin`` — the test starts device twins, the service or the
camera rig's processes (sockets, pseudo-terminals, network namespaces); ``browser`` — it
drives headless Chromium; ``slow`` — it takes seconds to tens of seconds. ``make check``
runs what is neither twin nor browser. No test reaches the network: what the network
brings (UR's RTDE client) is fetched by ``make`` beforehand, and the tests that use it
skip without it."""

from __future__ import annotations

import os
import tomllib
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from threadpoolctl import threadpool_limits  # type: ignore[import-untyped]

from cellcal.config import CellConfig, load_config
from tests.bundled_campaign import PRODUCER

#: BLAS (OpenBLAS) on one thread in the tests' processes and the processes they start
#: (cellcal's commands, the service, the twins), unless OPENBLAS_NUM_THREADS says
#: otherwise: the parallel run keeps every core busy with its workers already, and a
#: second BLAS thread only waits for a core, spinning (a tenth to a quarter more CPU time
#: for the same results on two cores).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
threadpool_limits(limits=int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")
#: OpenCV's own threads (remap, filters, detection) likewise, unless
#: OPENCV_FOR_THREADS_NUM says otherwise: its second thread costs a tenth more CPU time
#: where every core is busy with a worker (set before cv2 is first imported, which reads
#: it then, and passed on to the processes the tests start).
os.environ.setdefault("OPENCV_FOR_THREADS_NUM", "1")

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "cellcal" / "data"
#: the bundled cell less its rig: the tracker alone
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"
TABLE4_SRC = DATA / "paper_table4_station1.csv"
TABLE4_DST = DATA / "paper_table4_station2.csv"


#: Test files whose tests are independent of each other (no module fixture, no fixed
#: address): the parallel run hands out each of their tests to whichever worker is free.
#: Every other file's tests run on one worker, one after the other (they share module
#: fixtures, and some bind fixed addresses).
SPREAD = frozenset(
    {
        "tests/test_docs_examples.py",
        "tests/e2e/test_campaign.py",
        "tests/daemon/test_service.py",
        "tests/drivers/test_photogrammetry_sensor.py",
        "tests/daemon/test_shown_campaign.py",
        "tests/daemon/test_hostile_services.py",
    }
)


#: Folders whose files go to one worker together: they share session fixtures (the
#: fleet's PostgreSQL server and cells, made once instead of once per file).
TOGETHER = ("tests/fleet/",)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadfile``: by file, except the SPREAD files' tests one by one and the
    TOGETHER folders' files as one. Work goes out in collection order with
    ``--no-loadscope-reorder`` (see below)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class FileOrTest(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            folder = next((f for f in TOGETHER if path.startswith(f)), None)
            return nodeid if path in SPREAD else folder or path

    return FileOrTest(config, log)


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: three workers per core. Much of the suite's time is spent waiting
    (simulated dwell on a scaled clock, sockets, the service, Chromium), in which another
    worker on the core computes. On 2 cores: 4 workers 329 s, 5 workers 318 s, 6 workers
    298 s (that run also without the documents' examples compiling cellcal again), both
    cores busy for more of the run; an earlier machine had found 6 no faster than 4. With
    the suite's CPU cut to about 550 CPU-s: 5 workers 307 s, 6 workers 289–294 s, 8
    workers 320 s (more CPU: each worker collects the whole suite, 3 s).

    Two workers per core for a run without the twins' tests (``-m "not twin …"``, as
    ``make check``): those tests compute and seldom wait, and a third worker per core
    only adds its collection and the workers' contention for the caches. ``make check``'s
    tests on 2 cores: 6 workers 89 s (172 CPU-s), 4 workers 86 s (156 CPU-s), 3 workers
    93 s (the longest files end last)."""
    per_core = 2 if "not twin" in (config.getoption("markexpr", "") or "") else 3
    return per_core * len(os.sched_getaffinity(0))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """README's examples first (they run the bundled campaign that other tests read,
    tests/bundled_campaign.py), then the slow tests, so that the workers of the parallel
    run finish together; the files of each part in an order fixed by a checksum of
    their paths, not by folder. By folder, the drivers' tests (most of their time spent
    waiting out timeouts on purpose) came to every worker at once, and both cores
    stood half idle for a minute; shuffled so among the tests that compute, a waiting
    test's core is taken by another worker."""
    items.sort(
        key=lambda item: (
            item.nodeid != PRODUCER,
            item.get_closest_marker("slow") is None,
            zlib.crc32(item.nodeid.split("::", 1)[0].encode()),
        )
    )


def small_tracker_file(
    folder: Path, name: str, grid: list[int], samples: int, inside: int, **tables: Any
) -> Path:
    """The tracker cell (``config/mock-cell-tracker.toml``) on a smaller plan — ``grid``,
    ``samples`` per pose, ``inside`` validation poses, none outside the cube — with more
    ``tables`` (merged into a table of the same name), written as ``folder/name.toml``."""
    cell = tomllib.loads(TRACKER_CELL.read_text())
    cell["campaign"] |= {
        "grid": grid,
        "samples_per_pose": samples,
        "validation_inside": inside,
        "validation_per_region": 0,
    }
    for key, value in tables.items():
        cell[key] = {**cell.get(key, {}), **value}
    path = folder / f"{name}.toml"
    path.write_text(tomli_w.dumps(cell))
    return path


def tracker_cell() -> CellConfig:
    """The bundled simulated cell with the tracker alone (its database path as written)."""
    return load_config(TRACKER_CELL, relative_paths=False)


def load_xyz(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=(1, 2, 3))


@pytest.fixture
def table4() -> tuple[np.ndarray, np.ndarray]:
    return load_xyz(TABLE4_SRC), load_xyz(TABLE4_DST)


def rigid_problem(
    seed: int, n: int = 20, noise: float = 0.0, angle_deg: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Random src cloud (mm), true R, t and dst = R src + t + noise."""
    # scipy.spatial is slow to load: here, not in every worker's collection
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    P = rng.uniform(-100.0, 100.0, (n, 3)) + rng.uniform(-2000, 2000, 3)
    if angle_deg is None:
        R = Rotation.random(random_state=seed).as_matrix()
    else:
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    t = rng.uniform(-1500.0, 1500.0, 3)
    Q = P @ R.T + t + rng.normal(0.0, noise, (n, 3))
    return P, Q, R, t
