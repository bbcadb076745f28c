"""The measurement CSV's target, session and ori_w..ori_z columns and the model TOML's
scale and couple, through the command line: calibrate, the model file, predict."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cellcal.calib.error_model import Groups, State, predict
from cellcal.calib.geometry import so3_exp
from cellcal.calib.kinematics import target_kinematics
from cellcal.files.models import load_model
from cellcal.mocks.robot_truth import random_cell, random_joints
from tests.cli.test_calibrate_cli import run
from tests.lazy import Rotation

SMRS = np.array([[25.0, -40.0, 130.0], [-60.0, 35.0, 110.0]])


def _csv(path, q, m, targets=None, sessions=None, quats=None):
    head = [f"q{i}" for i in range(1, 7)] + ["x", "y", "z"]
    head += ["target"] if targets is not None else []
    head += ["session"] if sessions is not None else []
    head += ["ori_w", "ori_x", "ori_y", "ori_z"] if quats is not None else []
    rows = [",".join(head)]
    for k in range(len(q)):
        cells = [repr(math.degrees(v)) for v in q[k]] + [repr(float(v)) for v in m[k]]
        cells += [targets[k]] if targets is not None else []
        cells += [sessions[k]] if sessions is not None else []
        cells += [repr(float(v)) for v in quats[k]] if quats is not None else []
        rows.append(",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def cell():
    nominal = load_model("kuka-kr5-arc").model
    rng = np.random.default_rng(21)
    truth = random_cell(nominal, rng)
    frames = np.stack([truth.T_sensor_base, np.eye(4)])
    frames[1][:3, :3] = so3_exp(np.array([0.3, -1.2, 0.4]))
    frames[1][:3, 3] = [2500.0, -800.0, 300.0]
    return nominal, rng, truth, frames


def _measure(cell, n, targets, sessions):
    nominal, rng, truth, frames = cell
    q = random_joints(nominal, rng, n)
    g = Groups.of(n, targets, sessions)
    names_t = sorted(set(targets)) if targets else ["t"]
    target_offsets = SMRS[[names_t.index(t) for t in g.targets]] if targets else truth.target_offset
    names_s = sorted(set(sessions)) if sessions else ["s"]
    state = State(
        truth.model,
        target_offsets,
        frames[[names_s.index(s) for s in g.sessions], :3, :3],
        frames[[names_s.index(s) for s in g.sessions], :3, 3],
        np.zeros(3),
    )
    return q, predict(state, q, g) + rng.normal(0, 0.01, (n, 3))


def test_targets_and_sessions_through_calibrate_and_predict(capsys, tmp_path, cell):
    n = 100
    targets = ["A" if k % 2 else "B" for k in range(n)]
    sessions = ["s1" if k < 50 else "s2" for k in range(n)]
    q, m = _measure(cell, n, targets, sessions)
    data = _csv(tmp_path / "m.csv", q, m, targets, sessions)
    out = tmp_path / "cal.toml"
    code, stdout, err = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data, "--out", out, "--json"
    )
    assert code == 0, err
    doc = json.loads(stdout)
    assert set(doc["targets"]) == {"A", "B"} and set(doc["sessions"]) == {"s1", "s2"}
    assert doc["rms_after_mm"] < 0.02
    assert doc["validation"]["after"]["rms_mm"] < 0.03
    assert "target_offset_x:A" in {p["name"] for p in doc["parameters"]}
    text = out.read_text()
    assert "[[target]]" in text and "[[session]]" in text
    # predict picks each row's target and session by name and reproduces the data.
    joints = tmp_path / "j.csv"
    joints.write_text(
        "q1,q2,q3,q4,q5,q6,target,session\n"
        + "".join(
            ",".join(repr(math.degrees(v)) for v in q[k]) + f",{targets[k]},{sessions[k]}\n"
            for k in range(n)
        )
    )
    code, stdout, err = run(capsys, "predict", "--model", out, "--joints", joints)
    assert code == 0, err
    xyz = np.array([[float(v) for v in line.split(",")[6:9]] for line in stdout.splitlines()[1:]])
    assert float(np.sqrt(np.mean(np.sum((xyz - m) ** 2, axis=1)))) < 0.02
    # An unknown session in a joints file or a validation file is refused in one line.
    joints.write_text("q1,q2,q3,q4,q5,q6,session\n0,-90,90,0,45,0,s9\n")
    code, _, err = run(capsys, "predict", "--model", out, "--joints", joints)
    assert code == 2 and "session 's9' is not in the model" in err
    val = _csv(tmp_path / "v.csv", q[:10], m[:10], targets[:10], ["s3"] * 10)
    code, _, err = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data, "--validate", val
    )
    assert code == 2 and "another set-up" in err and len(err.strip().splitlines()) == 1


def test_orientation_columns_through_calibrate(capsys, tmp_path, cell):
    nominal, rng, truth, _ = cell
    q = random_joints(nominal, rng, 50)
    R_ft = so3_exp(np.radians([5.0, 10.0, -15.0]))
    k = target_kinematics(truth.model, q, truth.target_offset, jacobian=False)
    R = truth.T_sensor_base[:3, :3] @ k.R_flange @ R_ft
    xyzw = Rotation.from_matrix(R).as_quat()
    quats = xyzw[:, [3, 0, 1, 2]]
    data = _csv(tmp_path / "m6.csv", q, truth.positions(q), quats=quats)
    out = tmp_path / "cal6.toml"
    code, stdout, err = run(
        capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data, "--out", out, "--json"
    )
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["orientation_rms_deg"] < 1e-6
    assert {"target_rotation_x", "target_rotation_y", "target_rotation_z"} <= {
        p["name"] for p in doc["parameters"]
    }
    assert "rotation_vector_deg" in out.read_text()
    # A quaternion that is not of unit length is refused with its row.
    quats[3] *= 1.5
    _csv(data, q, truth.positions(q), quats=quats)
    code, _, err = run(capsys, "calibrate", "--model", "kuka-kr5-arc", "--data", data)
    assert code == 2 and "m6.csv:5:" in err and "not a unit quaternion" in err


def test_a_reversed_and_coupled_model_file(capsys, tmp_path):
    model = tmp_path / "fanuc-like.toml"
    rows = load_model("kuka-kr5-arc").model.joints
    text = 'name = "fanuc-like"\nconvention = "dh"\n'
    for i, j in enumerate(rows, start=1):
        text += (
            f"[[joint]]\na = {j.a}\nalpha = {math.degrees(j.alpha)}\nd = {j.d}\n"
            f"theta = {math.degrees(j.theta)}\n"
        )
        if i == 2:
            text += "scale = -1.0\n"
        if i == 3:
            text += "couple = { joint = 2, factor = 1.0 }\n"
    model.write_text(text)
    joints = tmp_path / "j.csv"
    joints.write_text("q1,q2,q3,q4,q5,q6\n10,-20,30,40,50,60\n")
    code, coupled, err = run(capsys, "predict", "--model", model, "--joints", joints)
    assert code == 0, err
    joints.write_text("q1,q2,q3,q4,q5,q6\n10,20,10,40,50,60\n")  # the angles themselves
    code, plain, err = run(capsys, "predict", "--model", "kuka-kr5-arc", "--joints", joints)
    assert coupled.splitlines()[1].split(",")[6:] == plain.splitlines()[1].split(",")[6:]


def test_the_command_list_is_lazy_and_its_help_lines_are_the_commands_own() -> None:
    """`cellcal --help` lists every subcommand from cellcal.cli's table without importing
    it: each line equals the command's own first sentence, however narrow the terminal;
    and `--version` and `--help` load none of numpy, OpenCV, scipy, matplotlib or
    Pinocchio (measured in a fresh interpreter)."""
    import subprocess
    import sys

    import click

    from cellcal.cli import COMMANDS, LazyGroup, cli

    ctx = click.Context(cli)
    group = cli
    assert isinstance(group, LazyGroup)
    for name, (_, line) in COMMANDS.items():
        real = group.get_command(ctx, name)
        assert real is not None
        for limit in (30, 45, 80, 400):
            assert click.Command(name, help=line).get_short_help_str(limit) == (
                real.get_short_help_str(limit)
            ), name
    heavy = ("numpy", "cv2", "scipy", "matplotlib", "pinocchio", "aiohttp")
    probe = (
        "import sys\nfrom cellcal.cli import main\n"
        "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))"
    )
    for args in (["--version"], ["--help"], ["rig", "--help"]):
        out = subprocess.run(
            [sys.executable, "-c", probe, *args], capture_output=True, text=True, timeout=60
        ).stdout.splitlines()[-1]
        if args[0] == "rig":
            assert "cv2" in out  # the group itself is loaded when it runs
        else:
            assert out == "[]", (args, out)
