"""FIGAROH (calibration on Pinocchio), the peer of benchmarks/calibration.py: importing
it (a benchmark-only extra, imported here and nowhere else), writing cellcal's model as
the URDF it reads, and running its calibration the way its examples do."""

from __future__ import annotations

import contextlib
import io
import logging
import math
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.calib.robot_model import RobotModel

Array = NDArray[np.float64]


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence FIGAROH's prints, warnings and log records (not part of what is timed)."""
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        logging.disable(logging.WARNING)
        try:
            yield
        finally:
            logging.disable(logging.NOTSET)


@dataclass(frozen=True)
class Figaroh:
    """The imported peer: the calibration class (cost function as in FIGAROH's examples),
    its FK function, its robot loader, versions, and the import time (excluded)."""

    calibration: type
    calc_updated_fkm: Callable[..., Any]
    load_robot: Callable[..., Any]
    version: str
    pin_version: str
    import_s: float


def import_figaroh() -> tuple[Figaroh | None, str]:
    t0 = time.perf_counter()
    try:
        with quiet():
            from figaroh.calibration.base_calibration import BaseCalibration
            from figaroh.calibration.calibration_tools import calc_updated_fkm
            from figaroh.target_offsets.load_robot import load_robot
    except Exception as exc:  # ImportError, or a binary extension that fails to load
        return None, f"{type(exc).__name__}: {exc}"
    import_s = time.perf_counter() - t0

    class TrackerCalibration(BaseCalibration):  # type: ignore[misc]
        """Position-only residuals (SE3 log map, metres), as in FIGAROH's examples."""

        def cost_function(self, var: Array) -> Array:
            self.n_evals = getattr(self, "n_evals", 0) + 1
            est = calc_updated_fkm(self.model, self.data, var, self.q_measured, self.calib_config)
            raw = self._compute_logmap_residuals(self.PEE_measured, est)
            out: Array = self.apply_measurement_weighting(raw, pos_weight=1.0, orient_weight=1.0)
            return out

    def version(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "?"

    fg = Figaroh(
        TrackerCalibration,
        calc_updated_fkm,
        load_robot,
        version("figaroh"),
        version("pin"),
        import_s,
    )
    return fg, ""


def _origin(T4: Array) -> str:
    """A URDF <origin> (metres, fixed-axis roll-pitch-yaw) of a 4×4 transform in mm."""
    xyz = " ".join(f"{v:.17g}" for v in T4[:3, 3] / 1000.0)
    rpy = " ".join(f"{v:.17g}" for v in Rotation.from_matrix(T4[:3, :3]).as_euler("xyz"))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def _elementary(kind: str, v: float) -> Array:
    T4 = np.eye(4)
    if kind in ("x", "y", "z"):
        T4[:3, :3] = Rotation.from_rotvec(np.eye(3)["xyz".index(kind)] * v).as_matrix()
    else:
        T4["XYZ".index(kind), 3] = v
    return T4


def model_urdf(model: RobotModel, target_offset: Array) -> str:
    """URDF of a cellcal model: joint i turns about z of its placement; the fixed rows of
    the DH (Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)) or MDH table are the placements, then a
    ``flange`` and a ``tool`` frame (the target, ``tool`` mm in the flange frame)."""
    e = _elementary
    placements: list[Array] = []
    if model.convention == "dh":
        prev = np.eye(4)
        for j in model.joints:
            placements.append(prev)
            prev = e("z", j.theta) @ e("Z", j.d) @ e("X", j.a) @ e("x", j.alpha) @ e("y", j.beta)
        flange = prev
    else:
        d_prev = 0.0
        for j in model.joints:
            placements.append(
                e("Z", d_prev) @ e("x", j.alpha) @ e("y", j.beta) @ e("X", j.a) @ e("z", j.theta)
            )
            d_prev = j.d
        flange = e("Z", d_prev)
    inertial = (
        '<inertial><mass value="1"/><origin xyz="0 0 0"/>'
        '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>'
    )
    out = ['<?xml version="1.0"?>', f'<robot name="{model.name}">']
    out.append(f'<link name="base_link">{inertial}</link>')
    parent = "base_link"
    for i, (j, P) in enumerate(zip(model.joints, placements, strict=True), start=1):
        lo = j.q_min if math.isfinite(j.q_min) else -2 * math.pi
        hi = j.q_max if math.isfinite(j.q_max) else 2 * math.pi
        out.append(
            f'<joint name="joint{i}" type="revolute"><parent link="{parent}"/>'
            f'<child link="link{i}"/>{_origin(P)}<axis xyz="0 0 1"/>'
            f'<limit lower="{lo!r}" upper="{hi!r}" effort="100" velocity="3"/></joint>'
        )
        out.append(f'<link name="link{i}">{inertial}</link>')
        parent = f"link{i}"
    out.append(
        f'<joint name="flange_joint" type="fixed"><parent link="{parent}"/>'
        f'<child link="flange"/>{_origin(flange)}</joint><link name="flange"/>'
    )
    T_tool = np.eye(4)
    T_tool[:3, 3] = target_offset
    out.append(
        '<joint name="tool_joint" type="fixed"><parent link="flange"/>'
        f'<child link="tool"/>{_origin(T_tool)}</joint><link name="tool"/>'
    )
    out.append("</robot>\n")
    return "\n".join(out)


CONFIG_YAML = """\
robot:
  name: "{name}"
  properties:
    joints:
      active_joints: [{joints}]
tasks:
  calibration:
    enabled: true
    parameters:
      calibration_level: "full_params"
      include_non_geometric: false
      outlier_threshold: 0.05
      random_seed: 0
    kinematics:
      base_frame: "universe"
      tool_frame: "tool"
    measurements:
      markers:
        - name: "smr"
          measurable_dof: [true, true, true, false, false, false]
      poses:
        base_pose: [0, 0, 0, 0, 0, 0]
        tool_pose: [0, 0, 0, 0, 0, 0]
    data:
      source_file: "{data}"
      validation_data_file: ""
      sample_configurations_file: ""
      number_of_samples: {n}
"""


@dataclass
class FigarohRun:
    """One FIGAROH calibration: wall times (s) of loading URDF and config, of
    ``initialize`` (data and parameter selection) and of the solve; the fitted
    parameters; and the calibration object, kept to predict."""

    fg: Figaroh
    calib: Any
    x: Array
    names: tuple[str, ...]
    absorbed: tuple[str, ...]
    renamed_base: tuple[str, ...]  # structural rows FIGAROH renamed to base_*
    load_s: float
    init_s: float
    solve_s: float
    repeats: int
    success: bool
    nfev: int
    n_evals: int

    @property
    def total_s(self) -> float:
        return self.load_s + self.init_s + self.solve_s

    def predict(self, q: Array, x: Array | None = None, names: list[str] | None = None) -> Array:
        """Target positions (mm) in the sensor frame for q (rad)."""
        cfg = dict(self.calib.calib_config, NbSample=len(q))
        if names is not None:
            cfg["param_name"] = names
        var = self.x if x is None else x
        with quiet():
            flat = self.fg.calc_updated_fkm(self.calib.model, self.calib.data, var, q, cfg)
        out: Array = np.asarray(flat, dtype=np.float64).reshape(3, len(q)).T * 1000.0
        return out


def run_figaroh(
    fg: Figaroh,
    nominal: RobotModel,
    q: Array,
    measured: Array,
    workdir: Path,
    *,
    urdf_tool: Array | None = None,
    repeats: int = 1,
) -> FigarohRun:
    """Calibrate with FIGAROH on the same arrays (converted to metres). Writing the URDF,
    the CSV and the YAML is not timed; loading them is."""
    tag = f"n{len(q)}_{time.perf_counter_ns()}"
    urdf = workdir / f"{tag}.urdf"
    data = workdir / f"{tag}.csv"
    config = workdir / f"{tag}.yaml"
    target_offset = nominal.target_offset if urdf_tool is None else urdf_tool
    urdf.write_text(model_urdf(nominal, np.asarray(target_offset, dtype=np.float64)))
    joints = [f"joint{i}" for i in range(1, nominal.dof + 1)]
    header = ",".join(["x1", "y1", "z1", *joints])
    table = np.hstack([measured / 1000.0, q])
    np.savetxt(data, table, delimiter=",", header=header, comments="", fmt="%.17g")
    config.write_text(
        CONFIG_YAML.format(name=nominal.name, joints=", ".join(joints), data=data, n=len(q))
    )
    best = (math.inf, 0.0, 0.0)
    calib: Any = None
    result: Any = None
    for _ in range(max(1, repeats)):
        with quiet():
            t0 = time.perf_counter()
            robot = fg.load_robot(str(urdf), load_by_urdf=True)
            calib = fg.calibration(robot, str(config))
            # Not read from the YAML by figaroh 1.0.2: the frames are unknown.
            calib.calib_config["known_baseframe"] = False
            calib.calib_config["known_tipframe"] = False
            t1 = time.perf_counter()
            calib.initialize()
            t2 = time.perf_counter()
            result, _ = calib.solve_optimisation(max_iterations=1)
            t3 = time.perf_counter()
        times = (t1 - t0, t2 - t1, t3 - t2)
        if sum(times) < sum(best):
            best = times
    cfg = calib.calib_config
    return FigarohRun(
        fg=fg,
        calib=calib,
        x=np.asarray(result.x, dtype=np.float64),
        names=tuple(cfg["param_name"]),
        absorbed=tuple(cfg.get("absorbed_param_name") or ()),
        renamed_base=tuple(cfg.get("base_frame_row_names") or ()),
        load_s=best[0],
        init_s=best[1],
        solve_s=best[2],
        repeats=max(1, repeats),
        success=bool(result.success),
        nfev=int(result.nfev),
        n_evals=int(getattr(calib, "n_evals", 0)),
    )
