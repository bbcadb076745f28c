"""``cellcal export urdf``: a robot model (calibrated or nominal) as URDF;
``cellcal export robot-program``: the program a robot's controller runs for its driver."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import click

from cellcal.calib.geometry import Array
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.term_effect import readings_within_limits, term_effects
from cellcal.commands.output import print_json, warn
from cellcal.errors import InputError
from cellcal.files.models import load_model, write_atomically
from cellcal.files.outputs import check_output_file
from cellcal.files.urdf import to_urdf

#: Readings (within the limits) at which a URDF export measures what it leaves out.
LOST_AT = 2000


def terms_lost(model: RobotModel, target_offset: Array) -> tuple[str, dict[str, Any]] | None:
    """A URDF holds geometry only: the line saying which error terms it leaves out and how
    far they move the target (at :data:`LOST_AT` readings within the limits, the
    calibration's payload, the campaign's start), and the same for --json; None without
    terms."""
    effects = term_effects(model, target_offset, readings_within_limits(model, LOST_AT))
    if not effects:
        return None
    every = effects[-1]
    names = ", ".join(
        f"{e.name} (joints {', '.join(map(str, e.joints))})" if e.joints != (0,) else e.name
        for e in effects[:-1]
    )
    line = (
        f"a URDF holds geometry only: the model's error terms — {names} — are left out; at "
        f"{LOST_AT} readings within the limits they move the target by {every.rms_mm:.3g} mm "
        f"RMS, {every.max_mm:.3g} mm at most, which a program using the URDF does not correct"
    )
    doc = {
        "terms": [e.name for e in effects[:-1]],
        "rms_mm": every.rms_mm,
        "max_mm": every.max_mm,
    }
    return line, doc


@click.group()
def export() -> None:
    """Write a robot model in another program's format, or the program a controller runs."""


@export.command("urdf")
@click.option(
    "--model", "model_spec", required=True, help="Built-in name, model TOML or calibrated model."
)
@click.option("--out", "out_path", required=True, help="Write the URDF here.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def export_urdf(model_spec: str, out_path: str, as_json: bool) -> None:
    """The model as URDF for ROS, MoveIt and Pinocchio: base_link, link_1..n turned by
    joint_1..n (values: the controller's readings), flange, target (the target offset
    on the flange) and, for a calibrated model, the sensor frame fixed to the base."""
    check_output_file(out_path)
    loaded = load_model(model_spec)
    text = to_urdf(loaded.model, loaded.target_offset, loaded.T_sensor_base)
    write_atomically(out_path, text)
    lost = terms_lost(loaded.model, loaded.target_offset)
    if lost is not None:
        warn(lost[0])
    frames = ["base_link", *(f"link_{i + 1}" for i in range(loaded.model.dof)), "flange", "target"]
    if loaded.T_sensor_base is not None:
        frames.append("sensor")
    if as_json:
        print_json(
            {
                "out": out_path,
                "model": loaded.model.name,
                "calibrated": loaded.calibrated,
                "joints": [f"joint_{i + 1}" for i in range(loaded.model.dof)],
                "links": frames,
                "frames": [
                    "flange",
                    "target",
                    *(["sensor"] if loaded.T_sensor_base is not None else []),
                ],
                "terms_left_out": None if lost is None else lost[1],
            }
        )
        return
    kind = "calibrated" if loaded.calibrated else "nominal"
    click.echo(f"{kind} model {loaded.model.name} as URDF in {out_path}: {', '.join(frames)}")


#: The drivers whose controller runs a program cellcal ships, and its folder in the
#: package (``cellcal/data/robot_programs/<driver>``).
ROBOT_PROGRAMS = ("kuka-kvp", "kuka-eki", "abb-rws")


@export.command("robot-program")
@click.option(
    "--driver",
    required=True,
    type=click.Choice(ROBOT_PROGRAMS),
    help="The robot driver whose controller-side program to write.",
)
@click.option("--out", "out_dir", required=True, help="Folder to write the files into.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def export_robot_program(driver: str, out_dir: str, as_json: bool) -> None:
    """The program that runs on the robot's controller for DRIVER (KRL, and the
    EthernetKRL channel's XML for kuka-eki; the RAPID module for abb-rws),
    to install as docs/robots.md says. Files already there are replaced."""
    folder = Path(out_dir)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out_dir}: cannot make the folder ({exc.strerror})") from None
    source = resources.files("cellcal") / "data" / "robot_programs" / driver
    written = []
    for item in sorted(source.iterdir(), key=lambda f: f.name):
        if item.is_file():
            write_atomically(folder / item.name, item.read_text(encoding="utf-8"))
            written.append(str(folder / item.name))
    if as_json:
        print_json({"driver": driver, "files": written})
        return
    click.echo(f"{driver}: wrote {', '.join(written)} (install: docs/robots.md)")
