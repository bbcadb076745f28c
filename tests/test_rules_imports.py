"""The layering of the design as import-linter contracts (``[tool.importlinter]`` in
pyproject.toml, ``make lint``): cellcal's own contracts, copied onto a small package of
the same shape, refuse each kind of forbidden import — direct or through another module
— naming the contract; the registry's lazy imports of the twins are its one exception;
and cellcal itself keeps every contract."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w

pytest.importorskip("importlinter", reason="import-linter (the dev extra) is not installed")

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _contracts() -> dict[str, Any]:
    with (ROOT / "pyproject.toml").open("rb") as f:
        return dict(tomllib.load(f)["tool"]["importlinter"])


def _lint(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _renamed(value: Any, old: str, new: str) -> Any:
    """cellcal's contracts with every module path under ``new`` instead of ``old``."""
    if isinstance(value, str):
        return value.replace(old, new)
    if isinstance(value, list):
        return [_renamed(v, old, new) for v in value]
    if isinstance(value, dict):
        return {k: _renamed(v, old, new) for k, v in value.items()}
    return value


#: A package shaped like cellcal: the registry (families.py) imports its twin lazily, as
#: cellcal's does (a twin in a folder of its own); the campaign and the commands reach the
#: twin through it; the service over the reports over the campaign over the store.
TOY = {
    "__init__.py": "",
    "cli.py": "",
    "families.py": """
        def serve():
            from toycell.mocks.robot.twin import serve

            return serve
        """,
    "helpers.py": "",
    "calib/__init__.py": "",
    "calib/fit.py": "",
    "drivers/__init__.py": "",
    "drivers/robot.py": "",
    "files/__init__.py": "",
    "files/points.py": "from toycell.calib import fit\n",
    "store/__init__.py": "",
    "store/database.py": "",
    "campaign/__init__.py": "",
    "campaign/devices.py": """
        from toycell import families
        from toycell.store import database

        def build():
            return families.serve()
        """,
    "reports/__init__.py": "",
    "reports/folder.py": "from toycell.campaign import devices\nfrom toycell.store import database",
    "service/__init__.py": "",
    "service/worker.py": "from toycell.campaign import devices\nfrom toycell.reports import folder",
    "commands/__init__.py": "",
    "commands/mock.py": "from toycell.families import serve\nfrom toycell.service import worker\n",
    "mocks/__init__.py": "",
    "mocks/robot/__init__.py": "",
    "mocks/robot/twin.py": "def serve():\n    return None\n",
}


def _toy(tmp_path: Path, changes: dict[str, str]) -> Path:
    for name, text in {**TOY, **changes}.items():
        path = tmp_path / "toycell" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    config = {"tool": {"importlinter": _renamed(_contracts(), "cellcal", "toycell")}}
    (tmp_path / "pyproject.toml").write_text(tomli_w.dumps(config))
    return tmp_path


def _name(contract_id: str) -> str:
    """The contract's name in the report (``toycell`` for ``cellcal``)."""
    contract = next(c for c in _contracts()["contracts"] if c["id"] == contract_id)
    return str(contract["name"]).replace("cellcal", "toycell")


def test_the_contracts_are_the_designs():
    contracts = {c["id"]: c for c in _contracts()["contracts"]}
    assert set(contracts) == {
        "calib-is-pure", "drivers-stand-alone", "twins-through-the-registry", "inner-walls",
    }  # fmt: skip
    above_calib = {"campaign", "store", "service", "reports", "drivers", "files", "mocks"}
    assert contracts["calib-is-pure"]["source_modules"] == ["cellcal.calib"]
    assert set(contracts["calib-is-pure"]["forbidden_modules"]) == {
        *(f"cellcal.{p}" for p in above_calib), "cellcal.commands", "cellcal.cli",
    }  # fmt: skip
    assert set(contracts["drivers-stand-alone"]["forbidden_modules"]) == {
        *(f"cellcal.{p}" for p in ("campaign", "store", "service", "reports", "mocks")),
        "cellcal.commands", "cellcal.cli",
    }  # fmt: skip
    registry = contracts["twins-through-the-registry"]
    assert set(registry["source_modules"]) == {
        f"cellcal.{p}" for p in ("campaign", "store", "service", "reports", "commands")
    }
    assert registry["forbidden_modules"] == ["cellcal.mocks"]
    assert contracts["inner-walls"]["layers"] == [
        f"cellcal.{p}" for p in ("cli", "commands", "service", "reports", "campaign", "store")
    ]
    # The one exception: the registry's own imports of the twins, at any depth.
    for c in contracts.values():
        assert c.get("ignore_imports", []) in ([], ["cellcal.families -> cellcal.mocks.**"])
        assert "allow_indirect_imports" not in c


def test_the_shape_of_cellcal_keeps_every_contract(tmp_path):
    result = _lint(_toy(tmp_path, {}), tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Contracts: 4 kept, 0 broken." in result.stdout


@pytest.mark.parametrize(
    ("contract", "changes", "chain"),
    [
        (
            "twins-through-the-registry",
            {"campaign/devices.py": "def build():\n    from toycell.mocks.robot.twin import serve"},
            "toycell.campaign.devices -> toycell.mocks.robot.twin",
        ),
        (
            # through another module: indirect imports count
            "twins-through-the-registry",
            {
                "helpers.py": "from toycell.mocks.robot import twin\n",
                "commands/mock.py": "from toycell import helpers\n",
            },
            "toycell.helpers -> toycell.mocks.robot.twin",
        ),
        (
            "calib-is-pure",
            {"calib/fit.py": "from toycell.drivers import robot\n"},
            "toycell.calib.fit -> toycell.drivers.robot",
        ),
        (
            "calib-is-pure",
            {"calib/fit.py": "def read():\n    from toycell.files import points\n"},
            "toycell.calib.fit -> toycell.files.points",
        ),
        (
            "drivers-stand-alone",
            {"drivers/robot.py": "import toycell.campaign.devices\n"},
            "toycell.drivers.robot -> toycell.campaign.devices",
        ),
        (
            "drivers-stand-alone",
            {"drivers/robot.py": "def twin():\n    import toycell.mocks.robot.twin\n"},
            "toycell.drivers.robot -> toycell.mocks.robot.twin",
        ),
        (
            "inner-walls",
            {"store/database.py": "from toycell.campaign import devices\n"},
            "toycell.store.database -> toycell.campaign.devices",
        ),
        (
            "inner-walls",
            {"campaign/devices.py": "def lock():\n    from toycell.service import worker\n"},
            "toycell.campaign.devices -> toycell.service.worker",
        ),
    ],
    ids=[
        "campaign-twin",
        "command-helper-twin",
        "calib-driver",
        "calib-files",
        "driver-campaign",
        "driver-twin",
        "store-over-campaign",
        "campaign-over-service",
    ],
)
def test_a_forbidden_import_fails_naming_the_contract(tmp_path, contract, changes, chain):
    result = _lint(_toy(tmp_path, changes), tmp_path)
    assert result.returncode != 0, result.stdout
    out = " ".join(result.stdout.split())  # the report wraps long names
    assert f"{_name(contract)} BROKEN" in out
    assert chain in out
    assert "Contracts: 3 kept, 1 broken." in out


def test_cellcal_keeps_its_contracts():
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    out = " ".join(result.stdout.split())
    for c in _contracts()["contracts"]:
        assert f"{c['name']} KEPT" in out


def test_the_registry_hands_out_the_twins_it_names():
    """Every name of ``TWIN_NAMES`` is the twin module's own object, and the registry
    refuses a name or a module of ``cellcal.mocks`` it does not hand out."""
    import importlib

    import cellcal.families as registry

    for name, module in registry.TWIN_NAMES.items():
        twin = importlib.import_module(f"cellcal.mocks.{module}")
        assert getattr(registry, name) is getattr(twin, name)
    for f in registry.FAMILIES:
        for path in (f.device, f.twin):
            if path is not None and path.startswith(registry.MOCKS):
                assert callable(registry.load(path))
    with pytest.raises(AttributeError, match="no attribute 'Nothing'"):
        registry.Nothing  # noqa: B018
    with pytest.raises(ValueError, match=r"cellcal\.mocks\.netns: not a module the registry"):
        registry.load("cellcal.mocks.netns:run_in_new_netns")
