"""Real robots' public laser-tracker data (tests/data/real, MIT).

Section 6 (:func:`print_real`): cellcal's calibration against the nominal model with
best-fit frames and against the exact-rank selection alone (what cellcal did before
identifiability became a matter of degree), measured in the same run on the source's
separate test poses.

Section 6b (:func:`print_layouts`): the calibration poses split into sessions, as a real
cell measures in several set-ups, by where their targets lie: a LINE (the fullest thin
cylinder), a CURVE (tube around a circle), a SURFACE (slab around a plane), each found
by seeded RANSAC, and the SCATTERED rest. Each session's measurements are moved by a
known rigid transform into its own sensor frame (exact: coordinates only). cellcal and
the plain fit (benchmarks/plain_fit.py) of the same parameters, on each layout alone and
all together, predict the source's held-out poses in the frame of the set-up validated
in (the scattered set-up keeps the source's frame).

    .venv/bin/python benchmarks/real_data.py
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import tempfile
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from plain_fit import PlainFit, plain_fit  # benchmarks/plain_fit.py, beside this script
from scipy.spatial.transform import Rotation
from session_layouts import (  # benchmarks/session_layouts.py, beside this script
    LAYOUTS,
    Layout,
    distance_change,
    moved,
    session_layouts,
)

import cellcal.calib.identification as identification
from cellcal.calib.error_model import Groups, predict
from cellcal.calib.geometry import Array
from cellcal.calib.identification import CalibrationResult, calibrate, fit_frames
from cellcal.calib.observations import on_a_line
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.validation import ErrorStats, Validation, held_out_groups, validate_on
from cellcal.cli import main as cellcal_main
from cellcal.errors import AcceptanceError, CellcalError, UserError
from cellcal.files.measurements import Measurements, read_measurements
from cellcal.files.models import load_model

REAL = Path(__file__).parents[1] / "tests" / "data" / "real"
ROBOTS = ("ur5", "barrett-wam")


def _exit(e: CellcalError) -> str:
    """A refusal in one line, with the exit code the CLI gives it."""
    code = 2 if isinstance(e, UserError) else 3 if isinstance(e, AcceptanceError) else "?"
    return f"refused, exit {code} ({type(e).__name__}): {e}"


def _largest(res: CalibrationResult) -> str:
    kin = [p for p in res.parameters if p.identified and p.kind != "target_offset"]
    mm = max(kin, key=lambda p: abs(p.value) if p.unit == "mm" else 0.0)
    deg = max(kin, key=lambda p: abs(p.value) if p.unit == "deg" else 0.0)
    return f"{mm.name} {mm.value:+.2f} mm, {deg.name} {deg.value:+.2f}°"


def _run(robot: str, *, exact_rank: bool) -> tuple[CalibrationResult, Validation, float]:
    nominal, data, val = (r := Robot.load(robot)).nominal, r.data, r.val
    saved = identification.weakly_determined
    if exact_rank:
        identification.weakly_determined = lambda J, s, ident: ident  # type: ignore[assignment]
    try:
        t0 = time.perf_counter()
        res = calibrate(nominal, data.q, data.xyz, accept=True)
        seconds = time.perf_counter() - t0
    finally:
        identification.weakly_determined = saved  # type: ignore[assignment]
    return res, validate_on(res, data.q, data.xyz, val.q, val.xyz), seconds


def print_real() -> None:
    print()
    print("== 6. Real robots (public laser-tracker data, held-out test poses of the source)")
    print(
        "   robot          poses  held-out RMS mm: nominal  cellcal  plain  exact-rank  "
        "ratio  | largest corrections (cellcal / exact-rank)"
    )
    for robot in ROBOTS:
        res, v, s = _run(robot, exact_rank=False)
        try:
            old, vo, _ = _run(robot, exact_rank=True)
            exact = f"{vo.after.rms:>12.4f}{v.after.rms / vo.after.rms:>7.2f}"
            largest, refused = f"{_largest(res)} / {_largest(old)}", ""
        except CellcalError as e:  # said below, not a traceback
            exact, largest, refused = f"{'—':>12}{'—':>7}", f"{_largest(res)} / —", _exit(e)
        r = Robot.load(robot)
        pf = plain_fit(r.nominal, r.data.q, r.data.xyz, res.covariance_specs)
        plain = ErrorStats.of(r.val.xyz - pf.predict(r.val.q)).rms
        print(
            f"   {robot:<14}{res.n_points:>6}  {v.before.rms:>22.4f}{v.after.rms:>9.4f}"
            f"{plain:>7.4f}{exact}  | {largest}"
        )
        weak = [p.name for p in res.parameters if p.at_nominal == "weak"]
        print(
            f"   {'':<14}hidden by the noise, left at nominal: {', '.join(weak) or 'none'}; "
            f"calibrate() {s * 1e3:.0f} ms, the plain fit of its parameters "
            f"{pf.seconds * 1e3:.0f} ms"
        )
        c = res.parameter_choice
        if c is not None:
            tempting = "; ".join(f"freeing {n} would give {cv:.4f} mm" for n, cv in c.tempting)
            print(
                f"   {'':<14}5-fold held-out error: the rule's set {c.rule_mm:.4f} mm, chosen "
                f"{c.chosen_mm:.4f} mm (freed: {', '.join(c.freed) or 'none'})"
                + (f"; {tempting}, beyond tolerance" if tempting else "")
            )
        if refused:
            print(f"   {'':<14}exact-rank: {refused}")


# ----------------------------------------------------------------- fits on the sessions


@dataclass(frozen=True)
class Robot:
    name: str
    nominal: RobotModel
    data: Measurements
    val: Measurements

    @classmethod
    def load(cls, name: str) -> Robot:
        nominal = load_model(str(REAL / name / "model.toml")).model
        data = read_measurements(REAL / name / "measurements.csv", nominal.dof)
        val = read_measurements(REAL / name / "validation.csv", nominal.dof)
        return cls(name, nominal, data, val)


def gather(robot: Robot, layouts: Sequence[Layout]) -> tuple[Array, Array, Groups]:
    """The layouts' joint readings, measurements (each in its own frame) and groups."""
    q = np.vstack([robot.data.q[s.rows] for s in layouts])
    m = np.vstack([moved(robot.data.xyz[s.rows], s.T) for s in layouts])
    return q, m, Groups.of(len(q), sessions=[s.name for s in layouts for _ in s.rows])


@dataclass(frozen=True)
class Row:
    label: str
    n: int
    did: tuple[str, ...]  # what cellcal did, one line each
    nominal: float = math.nan  # held-out RMS (mm) of the nominal with best-fit frames
    cellcal: float = math.nan
    plain: float = math.nan
    seconds: float = math.nan  # calibrate()
    pf: PlainFit | None = None
    result: CalibrationResult | None = None


def _summary(res: CalibrationResult) -> tuple[str, ...]:
    kinds = [s.kind for s in res.covariance_specs]
    frames, offsets = sum(k.startswith("frame") for k in kinds), kinds.count("target_offset")
    at = {w: [p.name for p in res.parameters if p.at_nominal == w] for w in ("rank", "weak")}
    fixed = sum(p.at_nominal == "fixed" for p in res.parameters)
    return (
        f"fitted {len(kinds)} parameters ({len(kinds) - frames - offsets} kinematic, {offsets} "
        f"offset, {frames} frame); at nominal: not identifiable {', '.join(at['rank']) or 'none'}"
        f"; hidden by the noise {', '.join(at['weak']) or 'none'}"
        + (f"; {fixed} fixed" if fixed else ""),
        *(f"warning: {w}" for w in res.warnings),
    )


def fit_row(
    robot: Robot,
    label: str,
    layouts: Sequence[Layout],
    *,
    fix: Collection[str] = (),
    model: RobotModel | None = None,
) -> Row:
    """cellcal (from ``model``, default the nominal, with ``fix``) and, without ``fix``,
    the plain fit of the same parameters on the layouts' sessions; held-out RMS on the
    source's test poses in the scattered set-up's frame (else the first layout's)."""
    q, m, g = gather(robot, layouts)
    ref = next((s for s in layouts if s.name == "scattered"), layouts[0])
    vq, vm = robot.val.q, moved(robot.val.xyz, ref.T)
    did: tuple[str, ...] = ()
    try:
        t0 = time.perf_counter()
        res = calibrate(model or robot.nominal, q, m, groups=g, fix=fix)
        seconds = time.perf_counter() - t0
    except AcceptanceError as e:  # said, and the numbers of the accepted result
        did = (_exit(e), "numbers below: the same with accept=True")
        t0 = time.perf_counter()
        res = calibrate(model or robot.nominal, q, m, groups=g, fix=fix, accept=True)
        seconds = time.perf_counter() - t0
    except CellcalError as e:
        return Row(label, len(q), (_exit(e),))
    held = held_out_groups(res, len(vq), sessions=[ref.name] * len(vq))
    try:
        v = validate_on(res, q, m, vq, vm, groups=held)
    except CellcalError as e:
        return Row(label, len(q), (*did, *_summary(res), f"validate_on: {_exit(e)}"), result=res)
    before = v.before.rms
    if model is not None:  # the baseline is the robot's nominal, not the given model
        base = fit_frames(robot.nominal, q, m, groups=g)
        before = ErrorStats.of(vm - predict(base, vq, held)).rms
    pf = None if fix else plain_fit(robot.nominal, q, m, res.covariance_specs, g)
    plain = math.nan if pf is None else ErrorStats.of(vm - pf.predict(vq, held)).rms
    return Row(label, len(q), did + _summary(res), before, v.after.rms, plain, seconds, pf, res)


def _csv(path: Path, q: Array, xyz: Array, sessions: Sequence[str]) -> None:
    cols = [f"q{j + 1}" for j in range(q.shape[1])]
    lines = [",".join(["name", *cols, "x", "y", "z", "session"])]
    for i, (qq, p, s) in enumerate(zip(np.degrees(q), xyz, sessions, strict=True)):
        lines.append(",".join([f"p{i}", *(f"{v:.17g}" for v in (*qq, *p)), s]))
    path.write_text("\n".join(lines) + "\n")


def command(robot: Robot, layouts: Sequence[Layout]) -> tuple[int, list[str], float]:
    """``cellcal calibrate --validate --json`` on the layouts' sessions (one CSV with a
    session column; the held-out poses in the scattered set-up): its exit code, its
    stderr lines and its held-out RMS after (NaN when it wrote none)."""
    q, m, g = gather(robot, layouts)
    ref = next(s for s in layouts if s.name == "scattered")
    out, err = io.StringIO(), io.StringIO()
    with tempfile.TemporaryDirectory() as tmp:
        cal, val = Path(tmp) / "sessions.csv", Path(tmp) / "validation.csv"
        _csv(cal, q, m, [g.sessions[s] for s in g.session])
        _csv(val, robot.val.q, moved(robot.val.xyz, ref.T), [ref.name] * len(robot.val.q))
        args = ["calibrate", "--model", str(REAL / robot.name / "model.toml")]
        args += ["--data", str(cal), "--validate", str(val), "--json"]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                cellcal_main(args)
                code = 0
            except SystemExit as e:
                code = int(e.code or 0)
    lines = [s.removeprefix("cellcal: ") for s in err.getvalue().splitlines()]
    rms = json.loads(out.getvalue())["validation"]["after"]["rms_mm"] if code == 0 else math.nan
    return code, lines, float(rms)


def _mm(v: float) -> str:
    return f"{v:>9.4f}" if np.isfinite(v) else f"{'—':>9}"


WIDTH = 34  # of a row's label


def _print_header() -> None:
    print(f"   {'':<{WIDTH}}{'':>5}  {'held-out RMS (mm)':^27}   {'time (ms)':^9}")
    print(
        f"   {'fit':<{WIDTH}}{'poses':>5}  {'nominal':>9}{'cellcal':>9}{'plain':>9}   "
        f"{'cellcal':>7} {'plain':>6} (evals, peak memory)"
    )


def _print_row(r: Row) -> None:
    pf = r.pf
    t_cal = f"{r.seconds * 1e3:>7.0f}" if np.isfinite(r.seconds) else f"{'—':>7}"
    t_pf = "" if pf is None else f"{pf.seconds * 1e3:>6.0f} ({pf.nfev} evals, "
    t_pf += "" if pf is None else f"{pf.peak_bytes / 2**20:.1f} MiB)"
    print(
        f"   {r.label:<{WIDTH}}{r.n:>5}  {_mm(r.nominal)}{_mm(r.cellcal)}{_mm(r.plain)}   "
        f"{t_cal} {t_pf or '—':>6}"
    )
    for line in r.did:
        print(f"   {'':<5}cellcal: {line}")
    if pf is not None and not pf.success:
        print(f"   {'':<5}plain fit: scipy says {pf.message}")
    res = r.result
    if pf is not None and res is not None:
        held = [p.name for p in res.parameters if p.kind == "target_offset" and not p.identified]
        if held:  # not fitted by either: each keeps the value it starts from
            xyz = ", ".join(f"{v:.1f}" for v in pf.state.target_offset)
            ours = ", ".join(f"{v:.1f}" for v in res.target_offset)
            print(
                f"   {'':<5}plain fit: {', '.join(held)} not fitted, so at the closed-form "
                f"start's value: offset ({xyz}) mm; cellcal's ({ours}) mm, {', '.join(held)} "
                "at the model's"
            )


def print_layouts(robots: Sequence[str] = ROBOTS) -> None:
    print()
    print("== 6b. Real robots in several set-ups: sessions cut from the calibration poses")
    print(
        "   by where their targets lie (RANSAC, seed 0), each in its own sensor frame (a known\n"
        "   rigid move); held-out: the source's test poses in the frame of the set-up validated\n"
        "   in (all together: the scattered one, the source's own frame). nominal = nominal\n"
        "   geometry with best-fit frames and offset; plain = scipy least_squares (lm, numeric\n"
        "   Jacobian) of cellcal's parameters from cellcal's closed-form start."
    )
    for name in robots:
        robot = Robot.load(name)
        lay = {s.name: s for s in session_layouts(robot.data.xyz)}
        x = robot.data.xyz
        change = max(distance_change(x, s.T) for s in lay.values())
        print(f"\n   {name}: {len(x)} calibration poses, {len(robot.val.q)} held out")
        for s in lay.values():
            turn = np.degrees(np.linalg.norm(Rotation.from_matrix(s.T[:3, :3]).as_rotvec()))
            where = (
                f"frame turned {turn:.0f}°, moved {np.linalg.norm(s.T[:3, 3]):.0f} mm"
                if s.name != "scattered"
                else "the source's frame"
            )
            print(f"     {s.name:<10}{len(s.rows):>4}  {s.how}; {where}")
        print(f"     (the moves change no pairwise distance by more than {change:.1e} mm)")
        _print_header()
        rows = {k: fit_row(robot, f"{k} alone", [s]) for k, s in lay.items()}
        for r in rows.values():
            _print_row(r)
        every = [lay[k] for k in LAYOUTS]
        _print_row(fit_row(robot, "all four, calibrate()", every))
        code, said, rms = command(robot, every)
        kept = [s for s in every if on_a_line(moved(robot.data.xyz[s.rows], s.T)) is None]
        _print_row(fit_row(robot, "all off a line (as the CLI fits)", kept))
        print(f"   {'':<5}`cellcal calibrate` on all four: exit {code}, held-out RMS {rms:.4f} mm")
        for line in said:
            print(f"   {'':<7}{line}")
        print(
            f"   {'':<5}fix tool: the target offset held at the model's value (where a "
            f"session leaves it undetermined)\n   {'':<5}fix kinematics, tool: only the "
            "set-up's frame fitted, on the scattered session's calibrated model (a new "
            f"set-up later)\n   {'':<5}(no plain fit with fix: its closed-form start does "
            "not hold the pinned values)"
        )
        cal = rows["scattered"].result
        for k in ("curve", "surface"):
            res = rows[k].result
            if res is not None and any(
                p.kind == "target_offset" and not p.identified for p in res.parameters
            ):
                _print_row(
                    fit_row(
                        robot, f"{k} alone, fix target_offset", [lay[k]], fix=("target_offset",)
                    )
                )
            if cal is not None:
                model = replace(
                    cal.calibrated,
                    target_offset_xyz=(
                        cal.target_offset[0],
                        cal.target_offset[1],
                        cal.target_offset[2],
                    ),
                )
                fix = ("kinematics", "target_offset")
                _print_row(
                    fit_row(robot, f"{k}, fix kinematics, tool", [lay[k]], fix=fix, model=model)
                )


if __name__ == "__main__":
    print_real()
    print_layouts()
