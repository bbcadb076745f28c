"""Optional dependencies per feature (pyproject.toml's extras, ``cellcal/extras.py``): in
a process where the optional libraries cannot be imported — as after ``pip install
cellcal``, or ``pip install "cellcal[modbus]"`` — the core runs (the tracker cell's
campaign, the calibration commands), and a feature whose library is missing ends in one
line naming the extra, exit 2."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from cellcal.extras import PROVIDERS

pytestmark = pytest.mark.slow  # a process per case: the parallel run starts it early

ROOT = Path(__file__).resolve().parents[1]
TRACKER_CELL = "config/mock-cell-tracker.toml"
UR5_URDF = "tests/data/urdf/ur5_robot.urdf"
JOINTS = "examples/ur5-joints.csv"
#: Every optional library's top-level module.
OPTIONAL = tuple(sorted(PROVIDERS))
#: What ``pip install "cellcal[modbus]"`` has of them.
MODBUS_ONLY = tuple(m for m in OPTIONAL if m != "pymodbus")

#: Loaded at start-up from PYTHONPATH: the top-level modules named in CELLCAL_TEST_BLOCK
#: (and theirs) are not installed — ModuleNotFoundError, as for a missing package.
SITECUSTOMIZE = """
    import os
    import sys
    from importlib.abc import MetaPathFinder

    BLOCKED = frozenset(os.environ.get("CELLCAL_TEST_BLOCK", "").split(","))


    class NotInstalled(MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None


    sys.meta_path.insert(0, NotInstalled())
    """


@pytest.fixture(scope="module")
def blocker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("blocker")
    (folder / "sitecustomize.py").write_text(textwrap.dedent(SITECUSTOMIZE))
    return folder


def _env(blocker: Path | None, blocked: tuple[str, ...]) -> dict[str, str]:
    env = dict(os.environ)
    if blocker is not None:
        path = [str(blocker), *filter(None, [env.get("PYTHONPATH")])]
        env.update(PYTHONPATH=os.pathsep.join(path), CELLCAL_TEST_BLOCK=",".join(blocked))
    return env


def _cellcal(
    blocker: Path, blocked: tuple[str, ...], *args: str
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cellcal", *args],
        cwd=ROOT,
        env=_env(blocker, blocked),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _python(
    blocker: Path | None, blocked: tuple[str, ...], code: str, *args: str
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        env=_env(blocker, blocked),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_the_blocker_blocks(blocker):
    result = _python(blocker, OPTIONAL, "import pymodbus.client")
    assert result.returncode == 1 and "ModuleNotFoundError: No module named 'pymodbus" in (
        result.stderr
    )


# ------------------------------------------------------------------ the core runs


def test_the_core_imports_no_optional_library(blocker):
    """The command line and the modules of the core features load without any of them,
    and leave them unimported."""
    code = textwrap.dedent(
        """
        import importlib, sys
        for m in [
            "cellcal.cli", "cellcal.config", "cellcal.families", "cellcal.files.models",
            "cellcal.files.urdf", "cellcal.campaign.devices", "cellcal.campaign.runner",
            "cellcal.store.database", "cellcal.drivers.tracker", "cellcal.drivers.ur",
            "cellcal.drivers.cameras.backends", "cellcal.commands.calibrate",
            "cellcal.commands.register", "cellcal.commands.predict", "cellcal.commands.plan",
            "cellcal.commands.models", "cellcal.commands.run", "cellcal.commands.mock",
            "cellcal.commands.rig_capture", "cellcal.commands.export",
            "cellcal.commands.tracker", "cellcal.commands.compensate",
            "cellcal.commands.iso9283", "cellcal.commands.service",
        ]:
            importlib.import_module(m)
        print(sorted(m for m in sys.modules if m.partition(".")[0] in sys.argv[1:]))
        """
    )
    # with the libraries installed, none is imported; without them, all loads the same
    for where in (None, blocker):
        result = _python(where, OPTIONAL, code, *OPTIONAL)
        assert result.returncode == 0, result.stderr
        assert result.stdout.strip() == "[]"


@pytest.mark.twin
def test_the_tracker_campaign_runs_with_the_modbus_extra_alone(blocker, tmp_path):
    """The Modbus robot and the laser tracker, each through its twin: pymodbus is the only
    optional library the tracker cell needs."""
    db = tmp_path / "campaign.db"
    result = _cellcal(
        blocker, MODBUS_ONLY, "run", "--mock", "--config", TRACKER_CELL, "--db", str(db)
    )
    assert result.returncode == 0, result.stderr
    assert "campaign 1 complete" in result.stdout
    assert db.is_file()


@pytest.mark.parametrize(
    "args",
    [
        (
            "register",
            "--src", "cellcal/data/paper_table4_station1.csv",
            "--dst", "cellcal/data/paper_table4_station2.csv",
        ),
        (
            "calibrate",
            "--model", "tests/data/real/ur5/model.toml",
            "--data", "tests/data/real/ur5/measurements.csv",
            "--validate", "tests/data/real/ur5/validation.csv",
        ),
        ("predict", "--model", "kuka-kr5-arc", "--joints", JOINTS),
        ("models",),
        ("--help",),
        ("mock", "tracker", "--help"),
    ],
    ids=["register", "calibrate", "predict", "models", "help", "mock-tracker-help"],
)  # fmt: skip
def test_the_calibration_commands_need_no_extra(blocker, args):
    result = _cellcal(blocker, OPTIONAL, *args)
    assert result.returncode == 0, result.stderr


def test_export_urdf_writes_without_pinocchio(blocker, tmp_path):
    """Writing URDF is cellcal's own XML; only reading it takes Pinocchio."""
    out = tmp_path / "kr5.urdf"
    result = _cellcal(
        blocker, OPTIONAL, "export", "urdf", "--model", "kuka-kr5-arc", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    assert out.read_text().startswith("<?xml")


# ------------------------------------------------- a missing extra: one line, exit 2


@pytest.mark.parametrize(
    ("blocked", "args", "line"),
    [
        (
            ("rtde_control", "rtde_receive"),
            ("run", "--mock", "--config", "config/mock-cell-ur10e.toml", "--db", "{tmp}/ur.db"),
            'cellcal: error: the robot driver "ur" needs ur-rtde: pip install "cellcal[ur]"',
        ),
        (
            ("pymodbus",),
            ("run", "--mock", "--config", TRACKER_CELL, "--db", "{tmp}/m.db"),
            'cellcal: error: the robot driver "modbus" needs pymodbus: '
            'pip install "cellcal[modbus]"',
        ),
        (
            ("cv2",),
            ("run", "--mock", "--db", "{tmp}/rig.db"),  # the bundled cell has a camera rig
            'cellcal: error: the photogrammetry driver "cameras" needs '
            'opencv-contrib-python-headless: pip install "cellcal[opencv]"',
        ),
        (
            ("matplotlib",),
            ("run", "--mock", "--config", TRACKER_CELL, "--db", "{tmp}/a.db", "--report", "{tmp}"),
            'cellcal: error: cellcal run --report needs matplotlib: pip install "cellcal[report]"',
        ),
        (
            ("matplotlib",),
            ("report", "--db", "{tmp}/none.db", "--campaign", "1", "--out", "{tmp}/r"),
            'cellcal: error: cellcal report needs matplotlib: pip install "cellcal[report]"',
        ),
        (
            ("pinocchio",),
            ("predict", "--model", UR5_URDF, "--joints", JOINTS),
            f"cellcal: error: reading URDF ({UR5_URDF}) needs pin: "
            'pip install "cellcal[urdf]"',
        ),
        (
            ("aiohttp",),
            ("daemon", "--mock"),
            'cellcal: error: cellcal daemon needs aiohttp: pip install "cellcal[service]"',
        ),
        (
            ("matplotlib",),
            ("daemon", "--mock", "--db", "{tmp}/d.db", "--socket", "{tmp}/s.sock"),
            'cellcal: error: cellcal daemon needs matplotlib: pip install "cellcal[report]"',
        ),
        (
            ("aiohttp",),
            ("campaign", "list"),
            'cellcal: error: cellcal campaign needs aiohttp: pip install "cellcal[service]"',
        ),
        (
            ("aiohttp",),
            ("service", "install", "--dry-run", "--config", TRACKER_CELL),
            'cellcal: error: the cell service needs aiohttp: pip install "cellcal[service]"',
        ),
        (
            ("cv2",),
            ("rig", "capture", "--mock", "--out", "{tmp}/sets"),
            "cellcal: error: cellcal rig needs opencv-contrib-python-headless: "
            'pip install "cellcal[opencv]"',
        ),
        (
            ("cv2",),
            ("mock", "cameras", "--rig", "config/mock-rig.toml", "--board", "board.toml"),
            "cellcal: error: cellcal mock cameras needs opencv-contrib-python-headless: "
            'pip install "cellcal[opencv]"',
        ),
        (
            ("psycopg",),
            ("fleet", "report", "--database", "postgresql://u@127.0.0.210:1/f", "--out", "{tmp}/f"),
            'cellcal: error: cellcal fleet report needs psycopg: pip install "cellcal[fleet]"',
        ),
    ],
    ids=[
        "ur", "modbus", "cameras", "run-report", "report", "urdf", "daemon", "daemon-report",
        "campaign",
        "service-install", "rig", "mock-cameras", "fleet",
    ],
)  # fmt: skip
def test_a_missing_extra_is_one_line_naming_it(blocker, tmp_path, blocked, args, line):
    result = _cellcal(blocker, blocked, *(a.replace("{tmp}", str(tmp_path)) for a in args))
    assert result.returncode == 2, result.stderr
    lines = [x for x in result.stderr.splitlines() if x.startswith("cellcal:")]
    assert lines == [line], result.stderr
    assert "Traceback" not in result.stderr
    # refused before any work: no database, no report (a robot claim's lock file at most)
    assert [p.name for p in tmp_path.iterdir() if p.suffix != ".lock"] == []


# ------------------------------------ a Modbus cell: its options are not its driver


def test_a_modbus_configuration_is_read_and_planned_without_pymodbus(blocker, tmp_path):
    """The Modbus robot's options live apart from its driver: a configuration with a
    Modbus robot is read and planned with no optional library at all, and driving the
    robot — a real cell's run — is refused before any work in one line naming the
    extra."""
    plan = _cellcal(blocker, OPTIONAL, "plan", "--config", TRACKER_CELL)
    assert plan.returncode == 0, plan.stderr
    assert "reachable" in plan.stdout and "Traceback" not in plan.stderr
    cell = tmp_path / "cell.toml"
    text = (ROOT / TRACKER_CELL).read_text()
    cell.write_text(text.replace("[robot]\n", '[robot]\naddress = "127.0.0.60:1502"\n', 1))
    run = _cellcal(blocker, OPTIONAL, "run", "--config", str(cell), "--db", str(tmp_path / "c.db"))
    assert run.returncode == 2, run.stderr
    lines = [x for x in run.stderr.splitlines() if x.startswith("cellcal:")]
    assert lines == [
        'cellcal: error: the robot driver "modbus" needs pymodbus: pip install "cellcal[modbus]"'
    ], run.stderr
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".lock") == ["cell.toml"]


@pytest.mark.twin
@pytest.mark.timeout(60)
def test_the_modbus_twin_serves_without_pymodbus(blocker):
    """``cellcal mock modbus-robot`` reads the configuration's Modbus robot and serves
    its twin, which speaks Modbus TCP by itself: pymodbus is the driver's, not the
    twin's. A Modbus request of the holding register 0 (the heartbeat) is answered."""
    twin = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "modbus-robot", "--listen", "127.0.0.61:0",
         "--config", TRACKER_CELL, "--time-scale", "0"],
        cwd=ROOT, env=_env(blocker, OPTIONAL), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert twin.stdout is not None
        where = twin.stdout.readline().strip()  # printed once it listens
        assert where.startswith("127.0.0.61:"), twin.communicate(timeout=10)[1]
        host, _, port = where.rpartition(":")
        with socket.create_connection((host, int(port)), timeout=10) as s:
            # MBAP: transaction 7, protocol 0, 6 bytes, device 1; read holding registers 0, 1
            s.sendall(bytes.fromhex("0007 0000 0006 01 03 0000 0001"))
            reply = s.recv(64)
        assert reply[:2] == b"\x00\x07" and reply[7:9] == b"\x03\x02" and len(reply) == 11
    finally:
        twin.send_signal(signal.SIGTERM)
        _, err = twin.communicate(timeout=20)
    # SIGTERM ends it (at once, if it comes before the command waits for it)
    assert twin.returncode in (0, -signal.SIGTERM), err
    assert "Traceback" not in err and "pymodbus" not in err


# ---------------------------------------------------------- the extras themselves


def _extras() -> dict[str, list[str]]:
    with (ROOT / "pyproject.toml").open("rb") as f:
        project = tomllib.load(f)["project"]
    return {"": project["dependencies"], **project["optional-dependencies"]}


def _names(requirements: list[str]) -> set[str]:
    return {r.split(">")[0].split("<")[0].split("=")[0].split("[")[0].strip() for r in requirements}


def test_every_optional_library_is_in_its_extra_and_not_in_the_core():
    extras = _extras()
    for module, (package, extra) in PROVIDERS.items():
        assert package in _names(extras[extra]), (module, extra)
        assert package in _names(extras["all"]), module
        assert package not in _names(extras[""]), module
    assert _names(extras["opencv"]) <= _names(extras["cameras"])


def test_all_is_every_feature_extra():
    extras = _extras()
    features = ("ur", "modbus", "abb", "opencv", "cameras", "urdf", "service", "report", "fleet")
    assert sorted(extras["all"]) == sorted({r for e in features for r in extras[e]})
