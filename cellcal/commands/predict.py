"""``cellcal predict``: target positions for joint readings."""

from __future__ import annotations

from collections.abc import Sequence

import click
import numpy as np

from cellcal.calib.error_model import Groups, Index, State, label_index
from cellcal.calib.error_model import predict as predict_positions
from cellcal.calib.geometry import Array
from cellcal.calib.observations import check_measurements
from cellcal.errors import InputError
from cellcal.files.measurements import format_positions, read_joints_labelled
from cellcal.files.models import load_model, write_atomically
from cellcal.files.outputs import check_output_file


def _pick(
    n: int, labels: Sequence[str] | None, known: dict[str, Array] | None, first: Array, what: str
) -> tuple[Array, Index]:
    """The values (stacked) and each of the n rows' index into them, by a label column;
    without the column, the first value for every row."""
    if labels is None:
        return first[None], np.zeros(n, dtype=np.intp)
    if not known:
        raise InputError(
            f"the joints file has a {what} column but the model has no named {what}s "
            f"(a calibrated model of data with a {what} column has)"
        )
    names = list(known)
    idx, missing = label_index(n, labels, names)
    if missing is not None:
        raise InputError(f"{what} {missing!r} is not in the model ({', '.join(names)})")
    return np.stack([known[k] for k in names]), idx


@click.command()
@click.option(
    "--model", "model_spec", required=True, help="Built-in name, model TOML or calibrated model."
)
@click.option(
    "--joints",
    "joints_path",
    required=True,
    help="CSV q1..qn in degrees; optional target and session columns pick a calibrated "
    "model's target offset and sensor frame by name; time_s, temperature_c and payload_kg "
    "are read by a model's error terms (absent: the campaign's start and the calibration's "
    "payload).",
)
@click.option("--out", "out_path", help="Write the CSV here instead of stdout.")
def predict(model_spec: str, joints_path: str, out_path: str | None) -> None:
    """Positions of the target (mm) for joint readings.

    With a calibrated model (from `cellcal calibrate --out`) the positions are in the
    measuring sensor's frame (of its first session and target, or those the
    joints file names); with a nominal model, in the robot base frame with the model's
    [tool] offset.
    """
    if out_path is not None:
        check_output_file(out_path)
    loaded = load_model(model_spec)
    rows = read_joints_labelled(joints_path, loaded.model.dof)
    q, targets, sessions = rows.q, rows.targets, rows.sessions
    check_measurements(loaded.model, q, np.zeros((len(q), 3)), None)
    T0 = np.eye(4) if loaded.T_sensor_base is None else loaded.T_sensor_base
    target_offsets, t_idx = _pick(len(q), targets, loaded.targets, loaded.target_offset, "target")
    frames, s_idx = _pick(len(q), sessions, loaded.sessions, T0, "session")
    groups = Groups(t_idx, s_idx)
    state = State(loaded.model, target_offsets, frames[:, :3, :3], frames[:, :3, 3], np.zeros(3))
    text = format_positions(q, predict_positions(state, q, groups, rows.conditions))
    if out_path is None:
        click.echo(text, nl=False)
    else:
        write_atomically(out_path, text)
