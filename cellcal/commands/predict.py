"""``cellcal predict``: target positions for joint readings."""

from __future__ import annotations

import click
import numpy as np

from cellcal.calib.error_model import State
from cellcal.calib.error_model import predict as predict_positions
from cellcal.calib.identification import check_measurements
from cellcal.measurementfiles import format_positions, read_joints
from cellcal.modelfiles import load_model, write_atomically


@click.command()
@click.option(
    "--model", "model_spec", required=True, help="Built-in name, model TOML or calibrated model."
)
@click.option("--joints", "joints_path", required=True, help="CSV q1..qn in degrees.")
@click.option("--out", "out_path", help="Write the CSV here instead of stdout.")
def predict(model_spec: str, joints_path: str, out_path: str | None) -> None:
    """Positions of the target (mm) for joint readings.

    With a calibrated model (from `cellcal calibrate --out`) the positions are in the
    measuring instrument's frame; with a nominal model, in the robot base frame with
    the model's [tool] offset.
    """
    loaded = load_model(model_spec)
    q = read_joints(joints_path, loaded.model.dof)
    check_measurements(loaded.model, q, np.zeros((len(q), 3)), None)
    T = np.eye(4) if loaded.T_instrument_base is None else loaded.T_instrument_base
    state = State(loaded.model, loaded.tool, T[:3, :3], T[:3, 3], np.zeros(3))
    text = format_positions(q, predict_positions(state, q))
    if out_path is None:
        click.echo(text, nl=False)
    else:
        write_atomically(out_path, text)
