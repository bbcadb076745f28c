"""What every device section of a cell configuration has in common.

A device family (``cellcal/families.py``) declares its options as a subclass of
:class:`RobotOptions` or :class:`SensorOptions` with its own ``driver`` (and, for a
sensor, ``kind``) as a one-value ``Literal``; ``config.py`` builds each section as a
union of the families' options discriminated by kind and driver, so an option that does
not belong to the chosen driver is refused with its path. Lengths mm, angles degrees.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Positive = Annotated[float, Field(gt=0)]
#: Seeds: what numpy's generators accept and SQLite stores.
Seed = Annotated[int, Field(ge=0, le=2**32 - 1)]
Name = Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]


class Strict(BaseModel):
    """Unknown keys, wrong types and NaN/inf are refused in every table of the file."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class RobotOptions(Strict):
    """The ``[robot]`` table every robot driver shares: its kinematic model (a built-in
    name or a model TOML file), where it is, how fast it moves and where it starts."""

    model: str = "kuka-kr5-arc"
    driver: str
    address: str = ""
    speed: Annotated[float, Field(gt=0, le=1)] = 0.25
    max_speed: Annotated[float, Field(gt=0, le=1)] = 0.5
    home_deg: list[float] = Field(default_factory=lambda: [0.0, -30.0, 40.0, 0.0, -20.0, 0.0])

    @model_validator(mode="after")
    def _speed(self) -> RobotOptions:
        if self.speed > self.max_speed:
            raise ValueError(f"speed {self.speed} exceeds max_speed {self.max_speed}")
        return self

    def relative_to(self, folder: Path) -> RobotOptions:
        """The options with the driver's relative file paths taken relative to ``folder``
        (the configuration file's); a driver with files overrides it."""
        return self

    def named_files(self) -> dict[str, str]:
        """The files the driver reads, by key (after :meth:`relative_to`); a driver with
        files overrides it."""
        return {}


class SensorOptions(Strict):
    """A ``[[sensor]]`` table every sensor driver shares: the sensor's name, kind and
    driver, where it is, how fast it samples, and the target it follows on the flange."""

    name: Name
    kind: str
    driver: str
    address: str = ""
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 10.0
    target_offset_mm: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    reference: bool = False

    def endpoint(self) -> str:
        """Where the device is reached ("" when not configured)."""
        return self.address

    def relative_to(self, folder: Path) -> SensorOptions:
        """The options with relative file paths taken relative to ``folder`` (the
        configuration file's); a driver with files overrides it."""
        return self

    def named_files(self) -> dict[str, str]:
        """The files the driver reads, by key (after :meth:`relative_to`); a driver with
        files overrides it."""
        return {}


class SimulatedRobotOptions(RobotOptions):
    """``driver = "simulated"``: the simulated cell's robot, moved in-process (mock mode
    only; a real cell has a real controller)."""

    driver: Literal["simulated"] = "simulated"
