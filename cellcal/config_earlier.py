"""Keys of earlier versions of a cell configuration, read as today's with one
deprecation line each (the table in ``docs/campaign.md``), so that a cell's file keeps
working across versions; and a configuration stored with a campaign by an earlier
version, upgraded so that its campaign can be resumed. (Apart from ``config.py``, which
validates today's keys.)"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import Any

from cellcal.errors import ConfigError
from cellcal.families import ROBOT, default_driver

Warn = Callable[[str], None]


def warn_on_stderr(line: str) -> None:
    """One warning line on stderr, as the CLI writes them."""
    print(f"cellcal: warning: {line}", file=sys.stderr)


def _toml(value: Any) -> str:
    """A value as TOML writes it (the scalars these keys hold)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return json.dumps(value, ensure_ascii=False, default=str)


def _port_in(address: str) -> int | None:
    """The port ``host:port`` names (an IPv6 host in brackets), as the drivers read it."""
    host, sep, port = address.rpartition(":")
    return int(port) if sep and port.isdigit() and not host.endswith(":") else None


class _Earlier:
    """One file's keys of earlier versions: the lines to warn with, and the refusal of
    an old key given with the key that replaced it."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.lines: list[str] = []

    def note(self, old: str, text: str) -> None:
        self.lines.append(f"{self.source}: {old} is deprecated, {text}")

    def refuse(self, old: str, new: str) -> ConfigError:
        return ConfigError(
            f"{self.source}: {old} is deprecated and {new} replaces it; both are given "
            f"(keep {new} only)"
        )

    def move(self, src: dict[str, Any], path: str, dst: dict[str, Any], new_path: str) -> None:
        """The key ``path`` names in ``src`` read as the one ``new_path`` names in ``dst``."""
        old, new = path.rpartition(".")[2], new_path.rpartition(".")[2]
        if old not in src:
            return
        if new in dst:
            raise self.refuse(path, new_path)
        dst[new] = src.pop(old)
        self.note(path, f"read as {new_path}; write {new} = {_toml(dst[new])}")

    def robot(self, robot: dict[str, Any]) -> dict[str, Any]:
        url_note = len(self.lines) if "url" in robot else None
        self.move(robot, "robot.url", robot, "robot.address")
        robot = self._robot(robot)
        if url_note is not None and url_note < len(self.lines):  # the address written last
            self.lines[url_note] = f"{self.source}: robot.url is deprecated, read as " + (
                f"robot.address; write address = {_toml(robot.get('address'))}"
            )
        return robot

    def _robot(self, robot: dict[str, Any]) -> dict[str, Any]:
        driver = robot.get("driver", default_driver("robot", ROBOT))
        if not isinstance(driver, str):
            return robot  # refused by validation
        if "settle_timeout_s" in robot and driver == "ur":
            self.move(robot, "robot.settle_timeout_s", robot, "robot.move_timeout_s")
        elif "settle_timeout_s" in robot:
            robot.pop("settle_timeout_s")
            self.note(
                "robot.settle_timeout_s",
                f'ignored: it timed the moves of driver = "ur" only (this robot: "{driver}"); '
                "delete it",
            )
        if "modbus" in robot and driver != "modbus":
            robot.pop("modbus")
            self.note(
                "[robot.modbus]",
                f'ignored: it mapped driver = "modbus" only (this robot: "{driver}"); delete it',
            )
        elif isinstance(robot.get("modbus"), dict):
            self.modbus(robot)
        return robot

    def modbus(self, robot: dict[str, Any]) -> None:
        """``[robot.modbus]`` is ``[robot.map]``, its port in ``robot.address``, its
        ``error`` the map's ``error_code``, its ``timeout_s`` ``robot.move_timeout_s``."""
        if "map" in robot:
            raise self.refuse("[robot.modbus]", "[robot.map]")
        table = dict(robot.pop("modbus"))
        self.note("[robot.modbus]", "read as [robot.map]; rename the table [robot.map]")
        self.move(table, "robot.modbus.error", table, "robot.map.error_code")
        self.move(table, "robot.modbus.timeout_s", robot, "robot.move_timeout_s")
        if "port" in table:
            self.port(robot, table.pop("port"))
        robot["map"] = table

    def port(self, robot: dict[str, Any], port: Any) -> None:
        old = "robot.modbus.port"
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port <= 0xFFFF:
            raise ConfigError(f"{self.source}: {old}: a port is 1..65535, got {port!r}")
        address = robot.get("address", "")
        if not isinstance(address, str):
            return  # refused by validation
        named = _port_in(address)
        if named is not None and named != port:
            raise ConfigError(
                f"{self.source}: {old} = {port} is deprecated and robot.address "
                f"{_toml(address)} names port {named}; keep robot.address only"
            )
        if named is not None:
            self.note(old, f"and robot.address {_toml(address)} names it already; delete it")
        elif address:
            host = f"[{address}]" if ":" in address and not address.startswith("[") else address
            robot["address"] = f"{host}:{port}"
            self.note(old, f"read as robot.address; write address = {_toml(robot['address'])}")
        else:
            self.note(old, f'ignored: robot.address is empty; write address = "HOST:{port}"')

    def sensor(self, sensor: dict[str, Any], i: int) -> dict[str, Any]:
        where = f"sensor.{i}"
        self.move(sensor, f"{where}.url", sensor, f"{where}.address")
        if sensor.get("driver") == "simulated" and sensor.get("kind") == "laser-tracker":
            sensor["driver"] = "line-protocol"
            self.note(
                f'{where}.driver = "simulated"',
                'read as "line-protocol" (mock mode serves the tracker\'s twin through it); '
                'write driver = "line-protocol"',
            )
        elif sensor.get("driver") == "simulated" and sensor.get("kind") == "photogrammetry":
            raise ConfigError(
                f'{self.source}: {where}.driver = "simulated" was the noise model of an '
                "earlier cellcal, which is gone: describe the rig's cameras "
                '(driver = "cameras", docs/photogrammetry.md)'
            )
        return sensor

    def simulation(self, simulation: dict[str, Any]) -> dict[str, Any]:
        if "rig_noise_mm" not in simulation:
            return simulation
        for new in ("rig_noise_grey", "rig_blur_px"):
            if new in simulation:
                raise self.refuse("simulation.rig_noise_mm", f"simulation.{new}")
        simulation.pop("rig_noise_mm")
        self.note(
            "simulation.rig_noise_mm",
            "ignored: the rig's images are rendered, with simulation.rig_noise_grey and "
            "rig_blur_px; delete it",
        )
        return simulation


def read_earlier_keys(
    data: dict[str, Any], source: str, warn: Warn | None = warn_on_stderr
) -> dict[str, Any]:
    """``data`` with the keys of earlier versions read as today's (the table in
    ``docs/campaign.md``): ``url`` is ``address``; ``[robot.modbus]`` is ``[robot.map]``
    (its ``port`` in ``robot.address``, ``error`` its ``error_code``, ``timeout_s``
    ``robot.move_timeout_s``); a UR's ``settle_timeout_s`` is ``move_timeout_s``, other
    robots ignored it; a laser tracker's ``driver = "simulated"`` is the line protocol
    its twin speaks; ``simulation.rig_noise_mm`` is ignored. One line each through
    ``warn`` (naming ``source``, the old key and the new); an old key given with the key
    that replaces it is a ConfigError. Any other key is left to validation."""
    e = _Earlier(source)
    out = dict(data)
    if isinstance(out.get("robot"), dict):
        out["robot"] = e.robot(dict(out["robot"]))
    sensors = out.get("sensor")
    if isinstance(sensors, list):
        out["sensor"] = [
            e.sensor(dict(s), i) if isinstance(s, dict) else s for i, s in enumerate(sensors)
        ]
    if isinstance(out.get("simulation"), dict):
        out["simulation"] = e.simulation(dict(out["simulation"]))
    if warn is not None:
        for line in e.lines:
            warn(line)
    return out


def upgrade_stored(data: dict[str, Any]) -> dict[str, Any]:
    """A configuration stored with a campaign by an earlier version, in today's keys, so
    that its campaign can be resumed (:func:`read_earlier_keys`, silently). A stored
    table holds every key, defaults too: a port in the address is the one the campaign
    used, whatever ``[robot.modbus]`` says."""
    for raw in data.get("sensor") or []:
        if raw.get("kind") == "photogrammetry" and raw.get("driver") == "simulated":
            raise ConfigError(
                f"sensor {raw.get('name')}: this campaign's rig was the noise model of an "
                "earlier cellcal, which is gone; it cannot be resumed (run it again)"
            )
    robot = data.get("robot")
    if (
        isinstance(robot, dict)
        and isinstance(robot.get("modbus"), dict)
        and _port_in(str(robot.get("address", ""))) is not None
    ):
        modbus = {k: v for k, v in robot["modbus"].items() if k != "port"}
        data = {**data, "robot": {**robot, "modbus": modbus}}
    return read_earlier_keys(data, "stored configuration", warn=None)
