"""The files a cell configuration names (a rig's calibration and target, a robot
driver's credentials), checked where a missing one would otherwise surface much later:
``cellcal service install`` and the service's start and SIGHUP. A missing rig file is
not a device that may come back: the service would retry it every 30 s for ever.
(``cellcal run`` reads them when it opens the devices, and refuses there.)"""

from __future__ import annotations

import os
from pathlib import Path

from cellcal.config import CellConfig
from cellcal.errors import ConfigError


def check_named_files(config: CellConfig, source: str) -> None:
    """Refuse, in one line naming the key, a file the configuration's devices read that
    is missing, not a file, or not readable by this process's user."""
    named = [(f"robot.{key}", path) for key, path in config.robot.named_files().items()]
    for i, sensor in enumerate(config.sensor, start=1):
        named += [(f"sensor.{i}.{key}", path) for key, path in sensor.named_files().items()]
    for key, path in named:
        why = _unusable(Path(path))
        if why:
            raise ConfigError(f"{source}: {key} = {path}: {why}")


def _unusable(path: Path) -> str:
    """Why the file cannot be read ("" when it can)."""
    if not path.exists():
        return "no such file"
    if not path.is_file():
        return "not a file"
    if not os.access(path, os.R_OK):
        return "not readable by this user"
    return ""
