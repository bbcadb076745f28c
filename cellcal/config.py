"""Cell and campaign configuration: TOML in, a frozen, typed value out.

Validation is strict (pydantic, ``extra="forbid"``): an unknown key is an error that
names its path (``campaign.dwel_s``), and so is a value of the wrong type or range.
Lengths are mm and angles degrees in the file, as everywhere a person writes.

The ``[robot]`` table and each ``[[sensor]]`` table are discriminated by their family
(kind and driver, ``cellcal/families.py``): each takes the keys its family's options
model declares and no other, so ``sensor.0.move_timeout_s`` is refused for a tracker.
Keys of earlier versions are read as today's first (``config_earlier.py``); the files a
configuration names are checked where they must exist (``config_files.py``).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, PlainValidator, SerializeAsAny, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from cellcal.calib.term_choice import parse_terms
from cellcal.check_config import CheckConfig
from cellcal.config_earlier import Warn, read_earlier_keys, warn_on_stderr
from cellcal.device_options import Positive, RobotOptions, Seed, SensorOptions, Strict, Vec3
from cellcal.errors import ConfigError, FileFormatError, InputError
from cellcal.families import ROBOT, Role, default_driver, families, find, kinds
from cellcal.files.text import read_toml
from cellcal.fleet_config import FleetConfig
from cellcal.simulation_config import SimulationConfig


def _choices(role: Role, kind: str | None = None) -> str:
    if kind is None:
        return ", ".join(kinds(role))
    return ", ".join(f.driver for f in families(role) if f.kind == kind)


def _no_family(role: Role, kind: Any, driver: Any) -> str:
    """Why no family matches a device section (a path relative to the section)."""
    if role == "sensor" and kind not in kinds("sensor"):
        if kind is None:
            return f"kind: required key missing ({_choices(role)})"
        return f"kind: {kind!r} is not a sensor kind ({_choices(role)})"
    what = "robot" if role == "robot" else f"{kind}"
    return f"driver: no {what} driver {driver!r} (choose {_choices(role, kind)})"


def _section(role: Role) -> Any:
    """The validator of a device section: the options model of its family (from kind
    and driver; a section that names no driver gets the first of its kind in the
    table), looked up when a file is read, so a driver is imported only when used."""

    def validate(value: Any) -> RobotOptions | SensorOptions:
        if isinstance(value, RobotOptions if role == "robot" else SensorOptions):
            return value
        if not isinstance(value, dict):
            raise PydanticCustomError("device_section", "expected a table")
        kind = ROBOT if role == "robot" else value.get("kind")
        fallback = default_driver(role, kind) if isinstance(kind, str) else None
        driver = value.get("driver", fallback)
        family = (
            find(role, kind, driver) if isinstance(kind, str) and isinstance(driver, str) else None
        )
        if family is None:
            raise PydanticCustomError("device_family", _no_family(role, kind, driver))
        out: RobotOptions | SensorOptions = family.options_model().model_validate(value)
        return out

    return validate


RobotSection = Annotated[SerializeAsAny[RobotOptions], PlainValidator(_section("robot"))]
SensorSection = Annotated[SerializeAsAny[SensorOptions], PlainValidator(_section("sensor"))]


class CampaignConfig(Strict):
    """The plan (the paper's cube and validation regions) and the acquisition rhythm."""

    cube_centre_mm: Vec3 = Field(default_factory=lambda: [750.0, 0.0, 1000.0])
    cube_edge_mm: Positive = 200.0
    grid: Annotated[list[Annotated[int, Field(ge=2, le=50)]], Field(min_length=3, max_length=3)] = (
        Field(default_factory=lambda: [4, 4, 5])
    )
    orientation_variation_deg: Annotated[float, Field(ge=0, le=90)] = 30.0
    # 0: every grid point; N: the N candidate poses that identify the model best
    optimal_poses: Annotated[int, Field(ge=0, le=10000)] = 0
    # which poses are optimal: D (the parameters' confidence volume, the default) or I
    # (the mean prediction variance inside the cube and in the validation regions)
    optimal_criterion: Literal["D", "I"] = "D"
    # where the robot will work, which the plan's expected error judges and optimal poses
    # are chosen from: "cube" (the paper's cube and the validation regions O1–O5) or
    # "workspace" (points drawn over the box workspace_min_mm..workspace_max_mm)
    region: Literal["cube", "workspace"] = "cube"
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
    # error terms beyond geometry the calibration may add: auto (each only when blocked
    # cross-validation accepts it), geometric, or a comma list (cellcal.calib.term_choice)
    terms: str = "auto"
    # measure the plan once per payload (kg), in this order, pausing before each new one
    # for the operator to mount it; none: the plan once, with whatever the robot carries
    payloads_kg: Annotated[list[Annotated[float, Field(ge=0, le=5000)]], Field(max_length=10)] = (
        Field(default_factory=list)
    )
    # repeated reference poses: this many, measured first, after every reference_every
    # poses and last (repeatability and drift, measured directly); 0: none
    reference_poses: Annotated[int, Field(ge=0, le=10)] = 0
    reference_every: Annotated[int, Field(ge=2, le=1000)] = 20
    # the warm-up gate: move through the plan's poses for this long (s of the campaign's
    # clock) before measuring, ending early once the robot's joint temperatures (where
    # its driver reads them) change less than warm_up_settled_c_per_min; 0: none
    warm_up_s: Annotated[float, Field(ge=0, le=7200)] = 0.0
    warm_up_settled_c_per_min: Annotated[float, Field(ge=0, le=10)] = 0.1

    @model_validator(mode="after")
    def _box(self) -> CampaignConfig:
        try:
            parse_terms(self.terms)
        except InputError as e:
            raise ValueError(str(e).replace("--terms", "terms")) from None
        if len(set(self.payloads_kg)) != len(self.payloads_kg):
            raise ValueError("payloads_kg: each payload once (the plan is measured per payload)")
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


def data_dir() -> Path:
    """Where cellcal writes what neither the command line nor the configuration places
    (the campaign database, the service's reports beside it): the service's systemd
    ``StateDirectory`` (``$STATE_DIRECTORY``, /var/lib/cellcal) when it runs in a unit
    that sets one, else ``$XDG_DATA_HOME/cellcal`` (an absolute ``XDG_DATA_HOME``), else
    ``~/.local/share/cellcal``. Never beside the configuration or the checkout."""
    state = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if state and Path(state).is_absolute():
        return Path(state)
    xdg = os.environ.get("XDG_DATA_HOME", "")
    if xdg and Path(xdg).is_absolute():
        return Path(xdg) / "cellcal"
    return Path.home() / ".local" / "share" / "cellcal"


def default_database() -> str:
    """The database of a configuration without ``storage.database``: ``cellcal.db`` in
    :func:`data_dir`."""
    return str(data_dir() / "cellcal.db")


class StorageConfig(Strict):
    #: absent: :func:`default_database`; relative: to the configuration file's folder
    database: str = Field(default_factory=default_database)


class CellConfig(Strict):
    """The whole configuration file."""

    name: str = "cell"
    robot: RobotSection = Field(default_factory=lambda: _default_robot())
    sensor: Annotated[list[SensorSection], Field(min_length=1)]
    campaign: CampaignConfig = Field(default_factory=CampaignConfig)
    storage: StorageConfig = Field(default_factory=StorageConfig)
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    check: CheckConfig = Field(default_factory=CheckConfig)
    fleet: FleetConfig | None = None

    @model_validator(mode="after")
    def _sensors(self) -> CellConfig:
        names = [s.name for s in self.sensor]
        if len(set(names)) != len(names):
            raise ValueError("sensor names must be unique")
        refs = [s.name for s in self.sensor if s.reference]
        if len(refs) != 1:
            raise ValueError(
                "exactly one sensor must have reference = true (the calibration "
                f"sensor); got {len(refs)}"
            )
        return self

    @property
    def reference_sensor(self) -> SensorOptions:
        return next(s for s in self.sensor if s.reference)


def _default_robot() -> RobotOptions:
    from cellcal.device_options import SimulatedRobotOptions

    return SimulatedRobotOptions()


#: Keys of earlier versions that reach validation all the same (in a table where they
#: never were, or not a table): the refusal names what replaced them.
RENAMED = {
    "url": "address",
    "settle_timeout_s": "move_timeout_s",
    "modbus": "map (the port went into robot.address, error into error_code, "
    "timeout_s into robot.move_timeout_s)",
    "rig_noise_mm": "rig_noise_grey and rig_blur_px (the rig's cameras are rendered)",
}


def _message(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = list(err["loc"])
    path = ".".join(str(p) for p in loc) or "(top level)"
    kind = err["type"]
    if kind == "device_family":
        return f"{path}.{err['msg']}"
    if kind == "extra_forbidden":
        hint = RENAMED.get(str(loc[-1]))
        return f"{path}: unknown key" + (f" (renamed: {hint})" if hint else "")
    if kind == "missing":
        return f"{path}: required key missing"
    return f"{path}: {str(err['msg']).removeprefix('Value error, ')}"


def config_from_dict(
    data: dict[str, object], source: str = "config", *, warn: Warn | None = warn_on_stderr
) -> CellConfig:
    """Validate a configuration; keys of earlier versions are read as today's, each
    with one line through ``warn`` (:func:`read_earlier_keys`)."""
    upgraded = read_earlier_keys(data, source, warn)
    try:
        return CellConfig.model_validate(upgraded)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {_message(exc)}") from None


def with_robot(config: CellConfig, **changes: Any) -> CellConfig:
    """The configuration with its robot table changed and validated again; a new
    ``driver`` keeps only the keys every robot driver shares."""
    robot = config.robot.model_dump()
    if "driver" in changes and changes["driver"] != robot["driver"]:
        robot = {k: v for k, v in robot.items() if k in RobotOptions.model_fields}
    return config_from_dict({**config.model_dump(), "robot": {**robot, **changes}}, "config")


def load_config(
    path: str | Path, *, relative_paths: bool = True, warn: Warn | None = warn_on_stderr
) -> CellConfig:
    """Read and validate a cell configuration file; relative paths in it are taken
    relative to its folder, made absolute (the folder with symlinks resolved, as
    ``cellcal campaign start --config`` names the file to the service), so the same
    file gives the same paths whatever the working folder (``relative_paths=False``:
    the database's is left as written). Keys of earlier versions are read as today's,
    one line each through ``warn`` (stderr). A file without ``storage.database`` gets
    :func:`default_database`, whose folder is made."""
    p = Path(path)
    try:
        data = read_toml(p)
    except FileFormatError as exc:
        raise ConfigError(str(exc)) from None
    config = config_from_dict(data, str(p), warn=warn)
    if "database" not in config.storage.model_fields_set:
        # the default database's folder (the user's data directory) is made here, once
        # a command's configuration relies on it
        with contextlib.suppress(OSError):  # said by the command that opens it
            Path(config.storage.database).parent.mkdir(parents=True, exist_ok=True)
    return relative_to(config, p.resolve().parent, database=relative_paths)


def relative_to(config: CellConfig, folder: Path, *, database: bool = True) -> CellConfig:
    """Relative file paths in a configuration (a robot model file, a robot driver's or a
    sensor's files, the database) are relative to the configuration file's folder, not to
    where the command runs."""
    from cellcal.files.models import builtin_names

    robot = config.robot
    if robot.model not in builtin_names() and not Path(robot.model).is_absolute():
        robot = robot.model_copy(update={"model": str(folder / robot.model)})
    robot = robot.relative_to(folder)
    storage = config.storage
    if database and not Path(storage.database).is_absolute():
        storage = storage.model_copy(update={"database": str(folder / storage.database)})
    sensors = [s.relative_to(folder) for s in config.sensor]
    return config.model_copy(update={"robot": robot, "storage": storage, "sensor": sensors})
