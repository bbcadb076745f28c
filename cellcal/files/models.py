"""Robot model files, read and written at the edge.

``--model`` is a built-in name (``kuka-kr5-arc``, ``ur5e``, ``ur10e``, shipped as
package data) or a TOML file in the contract's format; a calibrated model written by
``cellcal calibrate --out`` is also accepted. Writing is atomic: a temporary file in
the same folder, renamed over the target only once it is complete.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from cellcal import __version__
from cellcal.calib.drift import ModelUncertainty
from cellcal.calib.error_model import parameter_specs
from cellcal.calib.geometry import Array, so3_log
from cellcal.calib.identification import CalibrationResult
from cellcal.calib.outliers import PointResidual, point_residuals
from cellcal.calib.robot_model import RobotModel, model_from_dict, model_to_dict
from cellcal.calib.validation import Validation
from cellcal.errors import FileFormatError
from cellcal.extras import require
from cellcal.files.outputs import write_atomically as write_file_atomically
from cellcal.files.text import read_toml
from cellcal.plainvalues import plain

CALIBRATED_FORMAT = "cellcal-calibrated-model"
FORMAT_VERSION = 1

#: The target offset's parameter kinds in a calibrated model's ``[[parameter]]`` rows:
#: ``target_offset`` and, in files and databases written before the name was settled,
#: ``tool`` (still read).
TARGET_OFFSET_KINDS = frozenset({"target_offset", "tool"})


@dataclass(frozen=True)
class LoadedModel:
    """A model as read from ``--model``: the geometry, the target offset, and for a
    calibrated file the sensor frame (``T_sensor_base``, else None). A calibrated
    file of several targets or sessions also gives each one's offset (``targets``) and
    frame (``sessions``), by name; the first of each is ``target_offset`` and ``T_sensor_base``."""

    source: str
    model: RobotModel
    target_offset: Array
    T_sensor_base: Array | None
    calibrated: bool
    targets: dict[str, Array] | None = None
    sessions: dict[str, Array] | None = None


def builtin_names() -> list[str]:
    folder = resources.files("cellcal") / "data" / "models"
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))


def builtin_models() -> tuple[RobotModel, ...]:
    """Every built-in model (the alternatives an acceptance diagnosis tries)."""
    return tuple(load_model(n).model for n in builtin_names())


def _read_toml(path: Path, label: str) -> dict[str, Any]:
    if not path.exists() and not path.is_symlink():
        raise FileFormatError(
            f"{label}: no such file, and not a built-in model ({', '.join(builtin_names())})"
        )
    return read_toml(path, label=label)


def load_model(spec: str) -> LoadedModel:
    """A built-in model by name, a model / calibrated-model TOML file, or a URDF file
    (``*.urdf``: the chain to ``tool0``, see ``urdffiles``)."""
    if spec in builtin_names():
        ref = resources.files("cellcal") / "data" / "models" / f"{spec}.toml"
        with resources.as_file(ref) as p:
            data = _read_toml(p, spec)
        model = model_from_dict(data, spec)
        return LoadedModel(spec, model, model.target_offset, None, False)
    if spec.lower().endswith(".urdf"):
        from cellcal.files.urdf import model_from_urdf  # Pinocchio, only when asked

        require(f"reading URDF ({spec})", "pinocchio")
        urdf = model_from_urdf(spec)
        return LoadedModel(spec, urdf, urdf.target_offset, None, False)
    return _from_data(_read_toml(Path(spec), spec), spec)


def model_from_text(text: str, label: str) -> LoadedModel:
    """A model or calibrated model from its TOML text (a file's, sent or stored), named
    ``label`` in what it says."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FileFormatError(f"{label}: not valid TOML ({exc})") from None
    except RecursionError:
        raise FileFormatError(f"{label}: nested too deeply to be a cellcal file") from None
    return _from_data(data, label)


def _from_data(data: dict[str, Any], spec: str) -> LoadedModel:
    if data.get("format") == CALIBRATED_FORMAT:
        version = data.get("format_version")
        if version != FORMAT_VERSION:
            raise FileFormatError(f"{spec}: calibrated-model format_version {version!r} unknown")
        try:
            keys = ("name", "convention", "joint", "term")
            geometry: dict[str, Any] = {k: data[k] for k in keys if k in data}
            # [instrument]: what earlier versions called the sensor frame's table.
            frame = data["sensor"] if "sensor" in data else data["instrument"]
            matrix = np.array(frame["matrix"], dtype=np.float64)
            target_offset = np.array(data["tool"]["xyz"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise FileFormatError(f"{spec}: incomplete calibrated model ({exc})") from None
        if matrix.shape != (4, 4) or target_offset.shape != (3,) or not np.isfinite(matrix).all():
            raise FileFormatError(f"{spec}: sensor.matrix must be 4×4, tool.xyz 3 numbers")
        model = model_from_dict(geometry, spec)
        targets = _named(data, "target", spec, "xyz", (3,))
        sessions = _named(data, "session", spec, "matrix", (4, 4))
        return LoadedModel(spec, model, target_offset, matrix, True, targets, sessions)
    model = model_from_dict(data, spec)
    return LoadedModel(spec, model, model.target_offset, None, False)


def _named(
    data: dict[str, Any], key: str, spec: str, field: str, shape: tuple[int, ...]
) -> dict[str, Array] | None:
    """``[[target]]`` (name, xyz) or ``[[session]]`` (name, matrix) tables, by name."""
    if key not in data:
        return None
    out: dict[str, Array] = {}
    try:
        for row in data[key]:
            value = np.array(row[field], dtype=np.float64)
            if value.shape != shape or not np.isfinite(value).all():
                raise ValueError(f"{key}.{field} must be {'×'.join(map(str, shape))} numbers")
            out[str(row["name"])] = value
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{spec}: bad [[{key}]] table ({exc})") from None
    return out


def _groups_document(result: CalibrationResult) -> dict[str, Any]:
    """``[[target]]`` and ``[[session]]`` tables of a fit with several targets or sessions,
    or with orientations (each target's orientation on the flange)."""
    out: dict[str, Any] = {}
    if result.target_offsets is not None and (
        len(result.targets) > 1 or result.target_rotations is not None
    ):
        rows = []
        for k, name in enumerate(result.targets):
            row: dict[str, Any] = {"name": name or "target", "xyz": result.target_offsets[k]}
            if result.target_offsets_std is not None:
                row["std_mm"] = result.target_offsets_std[k]
            if result.target_rotations is not None:
                row["rotation_vector_deg"] = np.degrees(so3_log(result.target_rotations[k]))
            rows.append(row)
        out["target"] = rows
    if result.frames is not None and len(result.sessions) > 1:
        out["session"] = [
            {
                "name": name,
                "matrix": T,
                "rotation_vector_deg": np.degrees(so3_log(T[:3, :3])),
                "translation_mm": T[:3, 3],
            }
            for name, T in zip(result.sessions, result.frames, strict=True)
        ]
    return out


def _clean(value: Any) -> Any:
    """TOML has no null and no NaN: None values are dropped, NaN written as a string."""

    def drop_none(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: drop_none(x) for k, x in v.items() if x is not None}
        if isinstance(v, list | tuple):
            return [drop_none(x) for x in v]
        return v

    return plain(drop_none(value), str)


def _covariance_document(result: CalibrationResult) -> dict[str, Any] | None:
    """The fit's a-posteriori covariance of the parameters it identified (mm, deg; the
    sensor frame's rotation about ``pivot_mm``, in the sensor frame), from which a check
    predicts how well the model should match new poses (``calib/drift.py``); None when
    the fit has none."""
    cov, specs = result.covariance, result.covariance_specs
    if cov is None or not specs or not np.isfinite(cov).all():
        return None
    scale = np.array([s.display_factor for s in specs])
    pivot = result.pivots[0] if result.pivots is not None else np.zeros(3)
    return {
        "parameters": [s.name for s in specs],
        "matrix": cov * np.outer(scale, scale),
        "pivot_mm": pivot,
    }


def terms_document(result: CalibrationResult) -> dict[str, Any] | None:
    """What the calibration tried beyond geometry: the terms accepted, those rejected and
    why, and the blocked cross-validation RMS of the geometric and final models (mm)."""
    c = result.term_choice
    if c is None:
        return None
    return {
        "mode": c.mode,
        "accepted": list(c.accepted),
        "rejected": c.rejected,
        "blocked_cv_mm": {"geometric": c.geometric_cv_mm, "final": c.final_cv_mm},
    }


def calibrated_document(
    result: CalibrationResult,
    validation: Validation | None,
    data_path: str,
    points: Sequence[PointResidual] = (),
) -> dict[str, Any]:
    """The calibrated-model TOML document (mm, deg); ``points``: the per-point residuals
    of the fit (default: computed from the result, named by row number)."""
    geometry = model_to_dict(result.calibrated)
    T = result.T_sensor_base
    doc: dict[str, Any] = {
        "format": CALIBRATED_FORMAT,
        "format_version": FORMAT_VERSION,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "cellcal_version": __version__,
        "data": data_path,
        "name": geometry["name"],
        "convention": geometry["convention"],
        "joint": geometry["joint"],
        **({"term": geometry["term"]} if "term" in geometry else {}),
        "tool": {"xyz": result.target_offset, "std_mm": result.target_offset_std},
        "sensor": {
            "matrix": T,
            "rotation_vector_deg": np.degrees(so3_log(T[:3, :3])),
            "translation_mm": T[:3, 3],
            "std_rotation_deg": np.degrees(result.frame_std[:3]),
            "std_translation_mm": result.frame_std[3:],
        },
        **_groups_document(result),
        "nominal": model_to_dict(result.nominal),
        "parameter": [
            {
                "name": p.name,
                "joint": p.joint,
                "kind": p.kind,
                "unit": p.unit,
                "identified": p.identified,
                "error" if p.kind != "target_offset" else "value": p.value,
                "std": p.std,
                "at_nominal": p.at_nominal or None,
            }
            for p in result.parameters
        ],
        "fit": {
            "n_points": result.n_points,
            "dof": result.dof,
            "sigma0": result.sigma0,
            "weighted": result.weighted,
            "robust": result.robust if result.robust else "none",
            "rms_before_mm": result.rms_before,
            "rms_after_mm": result.rms_after,
            "max_after_mm": result.max_after,
            "condition_number": result.condition_number,
            "condition_number_equal_weights": result.condition_number_equal_weights,
            "identified": list(result.identified),
            "unidentifiable": list(result.unidentifiable),
            "correlated": [list(c) for c in result.identifiability.correlated],
            "warnings": list(result.warnings),
            "accepted_despite": list(result.accepted_despite),
            "covariance": _covariance_document(result),
            "terms": terms_document(result),
        },
        "point": [
            p.as_dict()
            for p in (
                points
                or point_residuals([str(k + 1) for k in range(result.n_points)], result.residuals)
            )
        ],
    }
    if validation is not None:
        doc["validation"] = {
            "method": validation.method,
            "n_points": validation.after.n,
            **{
                f"before_{k}_mm": getattr(validation.before, k)
                for k in ("mean", "rms", "max", "p95")
            },
            **{
                f"after_{k}_mm": getattr(validation.after, k) for k in ("mean", "rms", "max", "p95")
            },
        }
    out: dict[str, Any] = _clean(doc)
    return out


def write_atomically(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader sees the old file or the whole new one;
    an existing ``path`` that is not a regular file (a device, a FIFO, a socket, a
    folder) is refused and left as it was (``cellcal.files.outputs``)."""
    write_file_atomically(path, text)


def calibrated_toml(
    result: CalibrationResult,
    validation: Validation | None,
    data_path: str,
    points: Sequence[PointResidual] = (),
) -> str:
    """The calibrated-model file's text."""
    text = "# cellcal calibrated robot model: read by `cellcal predict --model FILE`.\n"
    text += "# Top-level name/convention/[[joint]]/[tool] are the calibrated geometry (mm, deg).\n"
    return text + tomli_w.dumps(calibrated_document(result, validation, data_path, points))


def write_calibrated(
    path: str | Path,
    result: CalibrationResult,
    validation: Validation | None,
    data_path: str,
    points: Sequence[PointResidual] = (),
) -> None:
    write_atomically(path, calibrated_toml(result, validation, data_path, points))


def model_uncertainty(text: str, label: str) -> ModelUncertainty:
    """What a calibrated model's text says of its own uncertainty (``[fit]`` and
    ``[fit.covariance]``): refused in one line for a model without it (not calibrated,
    or written by an earlier cellcal, which did not store the covariance)."""
    loaded = model_from_text(text, label)
    fit = tomllib.loads(text).get("fit", {})
    cov = fit.get("covariance") if isinstance(fit, dict) else None
    if not loaded.calibrated or not isinstance(cov, dict):
        raise FileFormatError(
            f"{label}: no covariance of its parameters ([fit.covariance]; a model "
            "calibrated by an earlier cellcal has none): a check cannot compute its "
            "limits; recalibrate"
        )
    if loaded.targets or loaded.sessions:
        raise FileFormatError(
            f"{label}: a model of several targets or sensor set-ups; a check compares with "
            "a model of one target and one sensor frame"
        )
    specs = {s.name: s for s in parameter_specs(loaded.model)}
    try:
        names = [str(n) for n in cov["parameters"]]
        chosen = tuple(specs[n] for n in names)
        matrix = np.array(cov["matrix"], dtype=np.float64)
        pivot = np.array(cov["pivot_mm"], dtype=np.float64)
        n, dof, rms_after = int(fit["n_points"]), int(fit["dof"]), float(fit["rms_after_mm"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{label}: a damaged [fit.covariance] ({exc})") from None
    P = len(chosen)
    ok = matrix.shape == (P, P) and pivot.shape == (3,) and dof > 0 and n > 0
    if not ok or not (np.isfinite(matrix).all() and np.isfinite(pivot).all()):
        raise FileFormatError(
            f"{label}: [fit.covariance] must be a finite {P}×{P} matrix with pivot_mm, "
            "and [fit] n_points and dof positive"
        )
    scale = np.array([1.0 / s.display_factor for s in chosen])
    noise = rms_after * math.sqrt(3 * n / dof)
    held_out = tomllib.loads(text).get("validation", {})
    validation = held_out.get("after_rms_mm") if isinstance(held_out, dict) else None
    if not isinstance(validation, int | float) or not math.isfinite(validation):
        validation = None
    return ModelUncertainty(
        chosen, matrix * np.outer(scale, scale), pivot, noise, validation and float(validation)
    )
