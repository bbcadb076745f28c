"""Configurations and devices of every registered family, for the contract suites: a
family is tested as the campaign uses it, built by the device factory from a cell
configuration — in mock mode, its driver against its twin."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

from cellcal.campaign.devices import Devices, build_devices
from cellcal.clock import SimulatedClock
from cellcal.config import CellConfig, config_from_dict, load_config
from cellcal.families import Family
from cellcal.files.models import load_model

CONFIG = Path(__file__).resolve().parents[2] / "config"


def bundled_cells() -> list[CellConfig]:
    folder = resources.files("cellcal") / "data"
    out = []
    for name in ("mock-cell.toml", "mock-cell-ur10e.toml"):
        with resources.as_file(folder / name) as path:
            out.append(load_config(path, relative_paths=False))
    return out


def cell_for(family: Family) -> CellConfig:
    """A bundled cell whose device of this family's role (for a sensor: its last)
    already uses it, the robot family's example cell in ``config/``, or the default cell
    with that device's driver replaced."""
    cells = bundled_cells()
    if family.role == "robot":
        for c in cells:
            if c.robot.driver == family.driver:
                return c
        shipped = CONFIG / f"mock-cell-{family.driver}.toml"
        if shipped.exists():  # the family's own example cell (its driver's required keys)
            return load_config(shipped, relative_paths=False)
        data: dict[str, Any] = cells[0].model_dump()
        keep = {"model", "speed", "max_speed", "home_deg", "address"}
        data["robot"] = {k: v for k, v in data["robot"].items() if k in keep}
        data["robot"]["driver"] = family.driver
        return config_from_dict(data, f"{family.tag} cell")
    for c in cells:
        last = c.sensor[-1]
        if (last.kind, last.driver) == (family.kind, family.driver):
            return c
    data = cells[0].model_dump()
    extra = {"name": "probe", "kind": family.kind, "driver": family.driver, "rate_hz": 20.0}
    data["sensor"] = [s for s in data["sensor"] if s["reference"]] + [extra]
    return config_from_dict(data, f"{family.tag} cell")


@contextlib.contextmanager
def mock_devices(config: CellConfig, seed: int = 5) -> Iterator[Devices]:
    nominal = load_model(config.robot.model).model
    devices = build_devices(config, nominal, SimulatedClock(), mock=True, seed=seed)
    try:
        yield devices
    finally:
        devices.close()
