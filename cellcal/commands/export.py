"""``cellcal export urdf``: a robot model (calibrated or nominal) as URDF."""

from __future__ import annotations

import click

from cellcal.commands.output import print_json
from cellcal.files.models import load_model, write_atomically
from cellcal.files.outputs import check_output_file
from cellcal.files.urdf import to_urdf


@click.group()
def export() -> None:
    """Write a robot model in another program's format."""


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
            }
        )
        return
    kind = "calibrated" if loaded.calibrated else "nominal"
    click.echo(f"{kind} model {loaded.model.name} as URDF in {out_path}: {', '.join(frames)}")
