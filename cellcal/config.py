"""Cell and campaign configuration: TOML in, a frozen, typed value out.

Validation is strict (pydantic, ``extra="forbid"``): an unknown key is an error that
names its path (``campaign.dwel_s``), and so is a value of the wrong type or range.
Lengths are mm and angles degrees in the file, as everywhere a person writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cellcal.errors import FileFormatError, UserError
from cellcal.textfiles import read_toml


class ConfigError(UserError):
    """A configuration file that cannot be used; the message names the key."""


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Positive = Annotated[float, Field(gt=0)]


#: Seeds: what numpy's generators accept and SQLite stores.
Seed = Annotated[int, Field(ge=0, le=2**32 - 1)]


class _Strict(BaseModel):
    # NaN and inf are refused in every number of the file (they would reach the plan).
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class ModbusConfig(_Strict):
    """A robot behind Modbus TCP: where its handshake registers are (holding registers,
    0-based) and how its float32 words are ordered (``docs/robots.md``)."""

    port: Annotated[int, Field(ge=1, le=65535)] = 502
    device_id: Annotated[int, Field(ge=0, le=255)] = 1
    word_order: Literal["big", "little"] = "big"
    heartbeat: Annotated[int, Field(ge=0, le=65535)] = 0
    status: Annotated[int, Field(ge=0, le=65535)] = 1
    error: Annotated[int, Field(ge=0, le=65535)] = 2
    ack: Annotated[int, Field(ge=0, le=65535)] = 3
    actual_joints: Annotated[int, Field(ge=0, le=65535)] = 10
    actual_pose: Annotated[int, Field(ge=0, le=65535)] = 30
    target_joints: Annotated[int, Field(ge=0, le=65535)] = 100
    target_pose: Annotated[int, Field(ge=0, le=65535)] = 112
    speed: Annotated[int, Field(ge=0, le=65535)] = 124
    command: Annotated[int, Field(ge=0, le=65535)] = 130
    sequence: Annotated[int, Field(ge=0, le=65535)] = 131
    timeout_s: Positive = 60.0


class RobotConfig(_Strict):
    """The robot: its model (built-in name or TOML file), its driver and address."""

    model: str = "kuka-kr5-arc"
    driver: Literal["simulated", "modbus", "ur"] = "simulated"
    address: str = ""
    speed: Annotated[float, Field(gt=0, le=1)] = 0.25
    max_speed: Annotated[float, Field(gt=0, le=1)] = 0.5
    home_deg: list[float] = Field(default_factory=lambda: [0.0, -30.0, 40.0, 0.0, -20.0, 0.0])
    settle_timeout_s: Positive = 60.0
    modbus: ModbusConfig = Field(default_factory=ModbusConfig)

    @model_validator(mode="after")
    def _speed(self) -> RobotConfig:
        if self.speed > self.max_speed:
            raise ValueError(f"speed {self.speed} exceeds max_speed {self.max_speed}")
        return self


class SensorConfig(_Strict):
    """One measuring instrument and the target it follows on the flange."""

    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]
    kind: Literal["laser-tracker", "photogrammetry"]
    driver: Literal["simulated", "line-protocol"] = "simulated"
    url: str = ""
    rate_hz: Annotated[float, Field(gt=0, le=1000)] = 10.0
    target_offset_mm: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    reference: bool = False


class CampaignConfig(_Strict):
    """The plan (the paper's cube and validation regions) and the acquisition rhythm."""

    cube_centre_mm: Vec3 = Field(default_factory=lambda: [750.0, 0.0, 1000.0])
    cube_edge_mm: Positive = 200.0
    grid: Annotated[list[Annotated[int, Field(ge=2, le=50)]], Field(min_length=3, max_length=3)] = (
        Field(default_factory=lambda: [4, 4, 5])
    )
    orientation_variation_deg: Annotated[float, Field(ge=0, le=90)] = 30.0
    dwell_s: Annotated[float, Field(ge=0, le=3600)] = 7.0
    samples_per_pose: Annotated[int, Field(ge=1, le=10000)] = 20
    validation_inside: Annotated[int, Field(ge=0, le=10000)] = 20
    validation_regions_mm: list[Vec3] = Field(
        default_factory=lambda: [
            [1000.0, 150.0, 550.0],
            [780.0, 710.0, 900.0],
            [780.0, 870.0, 410.0],
            [600.0, -800.0, 860.0],
            [940.0, -960.0, 450.0],
        ]
    )
    validation_per_region: Annotated[int, Field(ge=0, le=10000)] = 6
    validation_region_radius_mm: Positive = 200.0
    workspace_min_mm: Vec3 = Field(default_factory=lambda: [-1500.0, -1500.0, 0.0])
    workspace_max_mm: Vec3 = Field(default_factory=lambda: [1500.0, 1500.0, 2000.0])
    seed: Seed = 0

    @model_validator(mode="after")
    def _box(self) -> CampaignConfig:
        if any(
            lo >= hi for lo, hi in zip(self.workspace_min_mm, self.workspace_max_mm, strict=True)
        ):
            raise ValueError("workspace_min_mm must be below workspace_max_mm on every axis")
        for key in ("cube_edge_mm", "validation_region_radius_mm"):
            value = getattr(self, key)
            if value < 10.0:
                raise ValueError(
                    f"{key} = {value:g}: in millimetres, at least 10 (was it typed in metres?)"
                )
        return self


class StorageConfig(_Strict):
    database: str = "cellcal.db"


class SimulationConfig(_Strict):
    """The simulated cell's ground truth (mock mode only). Same seed, same campaign."""

    seed: Seed = 2018
    length_error_mm: Annotated[float, Field(ge=0)] = 0.3
    angle_error_deg: Annotated[float, Field(ge=0)] = 0.03
    tracker_position_mm: Vec3 = Field(default_factory=lambda: [2800.0, -600.0, 300.0])
    tracker_rotation_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 160.0])
    tracker_radial_um: Annotated[float, Field(ge=0)] = 10.0
    tracker_transverse_um_per_m: Annotated[float, Field(ge=0)] = 6.0
    rig_position_mm: Vec3 = Field(default_factory=lambda: [1900.0, 1200.0, 2200.0])
    rig_rotation_deg: Vec3 = Field(default_factory=lambda: [150.0, 20.0, -120.0])
    rig_noise_mm: Annotated[float, Field(ge=0)] = 0.05
    joint_speed_deg_s: Annotated[float, Field(gt=0, le=3600)] = 60.0


class CellConfig(_Strict):
    """The whole configuration file."""

    name: str = "cell"
    robot: RobotConfig = Field(default_factory=RobotConfig)
    sensor: Annotated[list[SensorConfig], Field(min_length=1)]
    campaign: CampaignConfig = Field(default_factory=CampaignConfig)
    storage: StorageConfig = Field(default_factory=StorageConfig)
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)

    @model_validator(mode="after")
    def _sensors(self) -> CellConfig:
        names = [s.name for s in self.sensor]
        if len(set(names)) != len(names):
            raise ValueError("sensor names must be unique")
        refs = [s.name for s in self.sensor if s.reference]
        if len(refs) != 1:
            raise ValueError(
                "exactly one sensor must have reference = true (the calibration "
                f"instrument); got {len(refs)}"
            )
        return self

    @property
    def reference_sensor(self) -> SensorConfig:
        return next(s for s in self.sensor if s.reference)


def _message(exc: ValidationError) -> str:
    err = exc.errors()[0]
    path = ".".join(str(p) for p in err["loc"]) or "(top level)"
    kind = err["type"]
    if kind == "extra_forbidden":
        return f"{path}: unknown key"
    if kind == "missing":
        return f"{path}: required key missing"
    return f"{path}: {str(err['msg']).removeprefix('Value error, ')}"


def config_from_dict(data: dict[str, object], source: str = "config") -> CellConfig:
    try:
        return CellConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {_message(exc)}") from None


def load_config(path: str | Path, *, relative_paths: bool = True) -> CellConfig:
    """Read and validate a cell configuration file; relative paths in it are taken
    relative to its folder (``relative_paths=False``: left as written, for the bundled
    cell, whose database belongs in the working folder)."""
    p = Path(path)
    try:
        data = read_toml(p)
    except FileFormatError as exc:
        raise ConfigError(str(exc)) from None
    config = config_from_dict(data, str(p))
    return _relative_to(config, p.parent) if relative_paths else config


def _relative_to(config: CellConfig, folder: Path) -> CellConfig:
    """Relative file paths in a configuration (a robot model file, the database) are
    relative to the configuration file's folder, not to where the command runs."""
    from cellcal.modelfiles import builtin_names

    robot = config.robot
    if robot.model not in builtin_names() and not Path(robot.model).is_absolute():
        robot = robot.model_copy(update={"model": str(folder / robot.model)})
    storage = config.storage
    if not Path(storage.database).is_absolute():
        storage = storage.model_copy(update={"database": str(folder / storage.database)})
    return config.model_copy(update={"robot": robot, "storage": storage})
