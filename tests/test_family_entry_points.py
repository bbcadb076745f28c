"""A family from another distribution, for real: a tiny distribution written into a
folder (``acme_cellcal``: the driver and the twin of a made-up probe of a new sensor
kind, ``acme-probe``, and ``acme_cellcal-0.1.dist-info`` with its entry point in the
group ``cellcal.families``), put on the path of ``python -m cellcal …``: the family is
listed, a configuration with it is read and planned, ``cellcal mock acme-probe`` serves
its twin, a short mock campaign measures with it, and the contract suite of the sensors
runs on it. Distributions that are no good — an import error, no Family, a clash with a
built-in family or a ``cellcal mock`` command, options that do not fit — are refused in
one line naming their entry point, and cellcal's own families go on working."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import cellcal.families as registry

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[1]
HOST = "127.0.0.62"

ACME = {
    "acme_cellcal/__init__.py": '''
        """Acme's family for cellcal: one line of the registry."""
        from cellcal.families import Family

        FAMILIES = [
            Family(
                "sensor", "acme-probe", "acme",
                options="acme_cellcal.driver:AcmeOptions",
                device="acme_cellcal.driver:AcmeProbe",
                twin="acme_cellcal.twin:serve",
                summary="Acme's touch probe, one line per point",
                mock="acme-probe",
            )
        ]
        ''',
    "acme_cellcal/driver.py": '''
        """The probe's driver: the line "M" asks, "x y z" (mm) answers."""
        from __future__ import annotations

        import socket
        from typing import Literal

        import numpy as np

        from cellcal.device_options import SensorOptions
        from cellcal.drivers.base import DeviceDescription, Series, host_port, label
        from cellcal.errors import DeviceError


        class AcmeOptions(SensorOptions):
            kind: Literal["acme-probe"] = "acme-probe"
            driver: Literal["acme"] = "acme"
            timeout_s: float = 2.0


        class AcmeProbe:
            def __init__(self, name, address, timeout_s, clock):
                self.name, self.address, self.timeout_s, self.clock = (
                    name, address, timeout_s, clock
                )
                self.sock = None

            @classmethod
            def from_options(cls, options, context):
                return cls(options.name, options.address, options.timeout_s, context.clock)

            def connect(self):
                try:
                    self.sock = socket.create_connection(
                        host_port(self.address, 7), self.timeout_s
                    )
                except OSError as exc:
                    raise DeviceError(
                        f"{label(self.name, self.address)}: {exc.strerror}", device=self.name
                    ) from None
                self.lines = self.sock.makefile("rw", newline="\\n")

            def measure(self, n, rate_hz):
                t0 = self.clock.now()
                xyz = []
                for _ in range(n):
                    self.lines.write("M\\n")
                    self.lines.flush()
                    xyz.append([float(v) for v in self.lines.readline().split()])
                self.clock.sleep(n / rate_hz)
                t = t0 + np.arange(n) / rate_hz
                return Series(self.name, t, t + 1.0, np.array(xyz))

            def describe(self):
                return DeviceDescription(self.name, "acme-probe/acme", self.address, "Acme")

            def close(self):
                if self.sock is not None:
                    self.lines.close()
                    self.sock.close()
                    self.sock = None
        ''',
    "acme_cellcal/twin.py": f'''
        """The probe's twin: its line protocol on {HOST}, points from the simulated cell."""
        import socketserver
        import threading

        from cellcal.mocks.twins import RunningTwin


        def serve(options, cell, time_scale):
            class Handler(socketserver.StreamRequestHandler):
                def handle(self):
                    for line in self.rfile:
                        if line.strip() == b"M":
                            x, y, z = cell.sample(options.name, 1)[0]
                            self.wfile.write(f"{{x:.6f}} {{y:.6f}} {{z:.6f}}\\n".encode())

            server = socketserver.ThreadingTCPServer(("{HOST}", 0), Handler)
            server.daemon_threads = True
            threading.Thread(target=server.serve_forever, daemon=True).start()

            class Stop:
                def stop(self):
                    server.shutdown()
                    server.server_close()

            host, port = server.server_address[:2]
            pointed = options.model_copy(update={{"address": f"{{host}}:{{port}}"}})
            return RunningTwin(pointed, Stop())
        ''',
    "acme_cellcal-0.1.dist-info/METADATA": """
        Metadata-Version: 2.1
        Name: acme-cellcal
        Version: 0.1
        """,
    "acme_cellcal-0.1.dist-info/entry_points.txt": """
        [cellcal.families]
        acme = acme_cellcal:FAMILIES
        """,
}

CELL = """
    name = "acme cell"
    [robot]
    model = "kuka-kr5-arc"
    driver = "simulated"
    home_deg = [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]
    [[sensor]]
    name = "probe"
    kind = "acme-probe"
    driver = "acme"
    rate_hz = 50.0
    timeout_s = 5.0
    target_offset_mm = [25.0, -40.0, 130.0]
    reference = true
    [campaign]
    grid = [2, 2, 3]
    dwell_s = 0.1
    samples_per_pose = 3
    validation_inside = 4
    validation_regions_mm = [[1000.0, 150.0, 550.0]]
    validation_per_region = 2
    """


def _bad(name: str, init: str) -> dict[str, str]:
    """A distribution ``<name>_cellcal`` whose entry point ``<name>`` is the ``FAMILIES``
    of a package made of ``init``."""
    return {
        f"{name}_cellcal/__init__.py": init,
        f"{name}_cellcal-0.1.dist-info/METADATA": f"Metadata-Version: 2.1\nName: {name}\n"
        "Version: 0.1\n",
        f"{name}_cellcal-0.1.dist-info/entry_points.txt": f"[cellcal.families]\n{name} = "
        f"{name}_cellcal:FAMILIES\n",
    }


#: Distributions cellcal refuses as it loads them, and the end of each one's line.
REFUSED = {
    "broken": (
        _bad("broken", "import acme_missing_library\n"),
        "refused: cannot import it (ModuleNotFoundError: No module named 'acme_missing_library')",
    ),
    "number": (
        _bad("number", "FAMILIES = 42\n"),
        "refused: its value is of type int, not a cellcal.families.Family or a sequence of them",
    ),
    "clash": (
        _bad(
            "clash",
            "from cellcal.families import Family\n"
            "FAMILIES = Family('sensor', 'laser-tracker', 'line-protocol', 'x:Options',"
            " 'x:Tracker', 'x:serve', 'a second line protocol')\n",
        ),
        "refused: the sensor family laser-tracker/line-protocol is cellcal's already",
    ),
    "command": (
        _bad(
            "command",
            "from cellcal.families import Family\n"
            "FAMILIES = (Family('robot', 'robot', 'ur-clone', 'x:Options', 'x:Robot',"
            " 'x:serve', 'a robot', mock='ur'),)\n",
        ),
        'refused: cellcal mock ur is cellcal\'s already (ur); set mock = "…"',
    ),
}


def _write(folder: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text).lstrip())


@pytest.fixture
def acme(tmp_path: Path) -> Path:
    """The folder that holds the acme distribution and a cell configuration using it."""
    _write(tmp_path / "site", ACME)
    (tmp_path / "acme.toml").write_text(textwrap.dedent(CELL))
    return tmp_path


def _env(*paths: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([*map(str, paths), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _cellcal(site: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cellcal", *args],
        cwd=ROOT,
        env=_env(site),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_the_family_of_a_distribution_is_listed_configured_and_run(acme):
    site, cell = acme / "site", str(acme / "acme.toml")
    # listed: cellcal mock has its twin, among cellcal's own
    listing = _cellcal(site, "mock", "--help")
    assert listing.returncode == 0, listing.stderr
    commands = listing.stdout.partition("Commands:")[2].split()
    for name in ("acme-probe", "cameras", "modbus-robot", "tracker", "ur"):
        assert name in commands
    assert listing.stderr == ""
    # a configuration with it is read, and its kind is one the configuration knows
    plan = _cellcal(site, "plan", "--config", cell)
    assert plan.returncode == 0, plan.stderr
    assert "reachable" in plan.stdout
    wrong = acme / "wrong.toml"
    wrong.write_text(textwrap.dedent(CELL).replace("timeout_s = 5.0", "beam_retries = 2"))
    refused = _cellcal(site, "plan", "--config", str(wrong))
    assert refused.returncode == 2
    assert refused.stderr.strip().endswith("sensor.0.beam_retries: unknown key")
    sonar = acme / "sonar.toml"
    sonar.write_text(textwrap.dedent(CELL).replace('kind = "acme-probe"', 'kind = "sonar"'))
    refused = _cellcal(site, "plan", "--config", str(sonar))
    assert refused.stderr.strip().endswith(
        "sensor.0.kind: 'sonar' is not a sensor kind (laser-tracker, photogrammetry, acme-probe)"
    )
    # a short mock campaign measures with it, through its driver against its twin
    db = acme / "acme.db"
    run = _cellcal(site, "run", "--mock", "--config", cell, "--db", str(db), "--json")
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["reference_sensor"] == "probe" and summary["n_poses"] == 12 + 4 + 2
    assert summary["rms_after_mm"] < summary["rms_before_mm"]
    # without the distribution, the same file names a kind cellcal does not know
    alone = _cellcal(acme / "nothing", "plan", "--config", cell)
    assert alone.returncode == 2
    assert alone.stderr.strip().endswith(
        "sensor.0.kind: 'acme-probe' is not a sensor kind (laser-tracker, photogrammetry)"
    )


def test_cellcal_mock_serves_the_twin_of_a_distribution(acme):
    twin = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "acme-probe", "--config", str(acme / "acme.toml"),
         "--seed", "3", "--time-scale", "0"],
        cwd=ROOT, env=_env(acme / "site"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert twin.stdout is not None
        where = twin.stdout.readline().strip()  # printed once it listens
        assert where.startswith(f"{HOST}:"), twin.communicate(timeout=10)[1]
        host, _, port = where.rpartition(":")
        with socket.create_connection((host, int(port)), timeout=10) as s:
            lines = s.makefile("rw", newline="\n")
            lines.write("M\n")
            lines.flush()
            xyz = [float(v) for v in lines.readline().split()]
        assert len(xyz) == 3 and 100.0 < sum(v * v for v in xyz) ** 0.5 < 1e5  # mm
    finally:
        twin.send_signal(signal.SIGTERM)
        _, err = twin.communicate(timeout=20)
    assert twin.returncode in (0, -signal.SIGTERM), err
    assert f"mock acme-probe/acme 'probe' of 'acme cell' serving on {where}" in err


def test_the_contract_suite_runs_on_the_family_of_a_distribution(acme):
    """The sensors' contract suite, collected with the distribution on the path,
    parametrises itself with the family too and passes."""
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-n", "0",
         "tests/drivers/test_sensor_contract.py", "-k", "acme"],
        cwd=ROOT, env=_env(acme / "site", ROOT), capture_output=True, text=True, timeout=150,
        check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 passed" in result.stdout


def test_bad_distributions_are_refused_in_a_line_each_and_break_nothing(acme):
    site = acme / "site"
    for files, _ in REFUSED.values():
        _write(site, files)
    result = _cellcal(site, "mock", "--help")
    assert result.returncode == 0, result.stderr
    warnings = sorted(result.stderr.splitlines())
    assert len(warnings) == len(REFUSED), result.stderr
    for line, (name, (_, end)) in zip(warnings, sorted(REFUSED.items()), strict=True):
        start = f"cellcal: warning: entry point {name} = {name}_cellcal:FAMILIES ({name} 0.1) "
        assert line == start + end
    # acme's family and cellcal's are all there, and cellcal's still run
    assert "acme-probe" in result.stdout and "tracker" in result.stdout
    plan = _cellcal(site, "plan", "--config", "config/mock-cell-tracker.toml")
    assert plan.returncode == 0 and "reachable" in plan.stdout, plan.stderr


def test_options_that_do_not_fit_their_line_are_one_line_when_used(acme):
    site = acme / "site"
    driver = site / "acme_cellcal" / "driver.py"
    driver.write_text(driver.read_text().replace('Literal["acme"] = "acme"', 'Literal["x"] = "x"'))
    result = _cellcal(site, "plan", "--config", str(acme / "acme.toml"))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (
        "cellcal: error: entry point acme = acme_cellcal:FAMILIES (acme-cellcal 0.1): options "
        "acme_cellcal.driver:AcmeOptions has driver 'x', not 'acme'"
    )
    (site / "acme_cellcal" / "twin.py").unlink()
    driver.write_text(driver.read_text().replace('Literal["x"] = "x"', 'Literal["acme"] = "acme"'))
    db = str(acme / "acme.db")
    run = _cellcal(site, "run", "--mock", "--config", str(acme / "acme.toml"), "--db", db)
    assert run.returncode == 2
    assert run.stderr.strip().splitlines()[-1] == (
        "cellcal: error: entry point acme = acme_cellcal:FAMILIES (acme-cellcal 0.1): cannot "
        "load acme_cellcal.twin:serve (No module named 'acme_cellcal.twin')"
    )


def test_the_registry_loads_the_distributions_once(acme, monkeypatch):
    """In this process: the entry points are read the first time a family is looked up,
    and not again; cellcal's table comes first."""
    monkeypatch.setattr(registry, "_INSTALLED", [])
    monkeypatch.syspath_prepend(str(acme / "site"))
    calls = []
    real = registry.entry_points

    def counted(**kwargs):
        calls.append(kwargs)
        return real(**kwargs)

    monkeypatch.setattr(registry, "entry_points", counted)
    try:
        sensors = registry.families("sensor")
        assert [f.tag for f in sensors] == [
            "laser-tracker/line-protocol",
            "laser-tracker/emscon",
            "photogrammetry/cameras",
            "acme-probe/acme",
        ]
        assert registry.find("sensor", "acme-probe", "acme") is sensors[-1]
        assert sensors[-1].origin == "entry point acme = acme_cellcal:FAMILIES (acme-cellcal 0.1)"
        assert calls == [{"group": "cellcal.families"}]
    finally:
        for name in [m for m in sys.modules if m.partition(".")[0] == "acme_cellcal"]:
            del sys.modules[name]
