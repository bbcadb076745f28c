"""Photogrammetry files, read and written at the edge: the rig (cameras), the target (the
marker fixture on the flange) and the ChArUco board, TOML in the contract's layout
(lengths mm, pixels px).

Reading is strict, like the configuration: an unknown key is an error naming its path
(``rig.toml: camera[2].dst: unknown key``), and every fault is one
:class:`~cellcal.errors.FileFormatError` line naming the file and the key. Tables of an
array (``[[camera]]``, ``[[marker]]``) are counted from 1. Writing is atomic, and a
written file reads back identically (floats are written with all their digits).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import tomli_w

from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Rig, Target
from cellcal.errors import FileFormatError, InputError
from cellcal.files.models import write_atomically
from cellcal.files.text import read_toml

__all__ = [
    "board_from_dict",
    "board_toml",
    "read_board",
    "read_rig",
    "read_target",
    "rig_from_dict",
    "rig_toml",
    "target_from_dict",
    "target_toml",
    "write_board",
    "write_rig",
    "write_target",
]

T = TypeVar("T")

_RIG = {"name"}
_CAMERA = {"name", "width", "height", "K", "dist", "T_rig_cam"}
_CAMERA_OPTIONAL = {"reprojection_rms_px"}
_TARGET = {"name", "dictionary"}
_TARGET_OPTIONAL = {"reference"}
_MARKER = {"id", "size", "T_target_marker"}
_BOARD = {"dictionary", "squares", "square", "marker"}
_BOARD_OPTIONAL = {"legacy"}


def _prefix(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _keys(
    path: Path, table: Mapping[str, Any], where: str, required: set[str], optional: set[str]
) -> None:
    """Refuse unknown keys and missing required ones, naming the first by its path."""
    unknown = [k for k in table if k not in required | optional]
    if unknown:
        raise FileFormatError(f"{path}: {_prefix(where, unknown[0])}: unknown key")
    missing = sorted(required - set(table))
    if missing:
        raise FileFormatError(f"{path}: {_prefix(where, missing[0])}: required key missing")


def _tables(path: Path, data: Mapping[str, Any], key: str) -> list[dict[str, Any]]:
    rows = data.get(key)
    if rows is None:
        raise FileFormatError(f"{path}: {key}: at least one [[{key}]] table is needed")
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise FileFormatError(f"{path}: {key}: expected [[{key}]] tables")
    return rows


def _bool_in(value: Any) -> bool:
    """A TOML boolean inside a list of numbers (numpy would read true as 1.0)."""
    if isinstance(value, list):
        return any(_bool_in(v) for v in value)
    return isinstance(value, bool)


def _build(path: Path, where: str, make: Callable[..., T], **fields: Any) -> T:
    """``make(**fields)``, its InputError (``KEY: what``) prefixed by file and table."""
    for key, value in fields.items():
        if isinstance(value, list) and _bool_in(value):
            raise FileFormatError(
                f"{path}: {_prefix(where, key)}: expected numbers, not true/false"
            )
    try:
        return make(**fields)
    except InputError as exc:
        raise FileFormatError(f"{path}: {_prefix(where, str(exc))}") from None


def _data(path: str | Path) -> tuple[Path, dict[str, Any]]:
    p = Path(path)
    return p, read_toml(p)


# --- reading ---------------------------------------------------------------------------


def rig_from_dict(data: Mapping[str, Any], path: str | Path = "rig") -> Rig:
    """A rig from the contract's TOML structure (``name``, ``[[camera]]``)."""
    p = Path(path)
    _keys(p, data, "", _RIG, {"camera", "accepted_despite"})
    failed = data.get("accepted_despite", [])
    if not isinstance(failed, list) or not all(isinstance(f, str) for f in failed):
        raise FileFormatError(f"{p}: accepted_despite: expected a list of strings")
    cameras = []
    for k, row in enumerate(_tables(p, data, "camera"), start=1):
        where = f"camera[{k}]"
        _keys(p, row, where, _CAMERA, _CAMERA_OPTIONAL)
        cameras.append(_build(p, where, Camera, **row))
    return _build(p, "", Rig, name=data["name"], cameras=tuple(cameras))


def target_from_dict(data: Mapping[str, Any], path: str | Path = "target") -> Target:
    """A target from the contract's TOML structure (``name``, ``dictionary``,
    ``reference`` (default: the origin), ``[[marker]]``)."""
    p = Path(path)
    _keys(p, data, "", _TARGET, _TARGET_OPTIONAL | {"marker"})
    markers = []
    for k, row in enumerate(_tables(p, data, "marker"), start=1):
        where = f"marker[{k}]"
        _keys(p, row, where, _MARKER, set())
        markers.append(_build(p, where, Marker, **row))
    return _build(
        p,
        "",
        Target,
        name=data["name"],
        dictionary=data["dictionary"],
        reference=data.get("reference", [0.0, 0.0, 0.0]),
        markers=tuple(markers),
    )


def board_from_dict(data: Mapping[str, Any], path: str | Path = "board") -> Board:
    """A ChArUco board from the contract's TOML structure."""
    p = Path(path)
    _keys(p, data, "", _BOARD, _BOARD_OPTIONAL)
    squares = data["squares"]
    if not isinstance(squares, list):
        raise FileFormatError(f"{p}: squares: expected [nx, ny], integers of at least 2")
    return _build(p, "", Board, **{**data, "squares": tuple(squares)})


def read_rig(path: str | Path) -> Rig:
    """The rig file (``rig calibrate --out``, read by ``rig measure`` and the campaign)."""
    p, data = _data(path)
    return rig_from_dict(data, p)


def read_target(path: str | Path) -> Target:
    """The target file: the marker fixture on the flange."""
    p, data = _data(path)
    return target_from_dict(data, p)


def read_board(path: str | Path) -> Board:
    """The board file (``rig calibrate --board``)."""
    p, data = _data(path)
    return board_from_dict(data, p)


# --- writing ---------------------------------------------------------------------------


def _toml(value: Any) -> str:
    """One TOML value: arrays on one line (matrices row by row), floats with every digit."""
    if isinstance(value, np.ndarray):
        return _toml(value.tolist())
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return repr(float(value))  # finite: the dataclasses refuse anything else
    return tomli_w.dumps({"v": value})[len("v = ") : -1]


def _lines(table: Mapping[str, Any]) -> list[str]:
    return [f"{k} = {_toml(v)}" for k, v in table.items() if v is not None]


def rig_toml(rig: Rig, accepted_despite: Sequence[str] = ()) -> str:
    """The rig file's text."""
    out = ["# cellcal camera rig (mm, px; OpenCV conventions): read by `rig measure`.", ""]
    out += _lines({"name": rig.name})
    if accepted_despite:
        out += _lines({"accepted_despite": list(accepted_despite)})
    for cam in rig.cameras:
        out += ["", "[[camera]]"]
        out += _lines(
            {
                "name": cam.name,
                "width": cam.width,
                "height": cam.height,
                "K": cam.K,
                "dist": cam.dist,
                "T_rig_cam": cam.T_rig_cam,
                "reprojection_rms_px": cam.reprojection_rms_px,
            }
        )
    return "\n".join(out) + "\n"


def target_toml(target: Target) -> str:
    """The target file's text."""
    out = ["# cellcal marker target (mm): the marker fixture on the flange.", ""]
    out += _lines(
        {"name": target.name, "dictionary": target.dictionary, "reference": target.reference}
    )
    for m in target.markers:
        out += ["", "[[marker]]"]
        out += _lines({"id": m.id, "size": m.size, "T_target_marker": m.T_target_marker})
    return "\n".join(out) + "\n"


def board_toml(board: Board) -> str:
    """The board file's text."""
    out = ["# cellcal ChArUco board (mm).", ""]
    out += _lines(
        {
            "dictionary": board.dictionary,
            "squares": board.squares,
            "square": board.square,
            "marker": board.marker,
            "legacy": board.legacy,
        }
    )
    return "\n".join(out) + "\n"


def write_rig(path: str | Path, rig: Rig, accepted_despite: Sequence[str] = ()) -> None:
    """The rig file; ``accepted_despite`` records the checks it failed (``--accept``)."""
    write_atomically(path, rig_toml(rig, accepted_despite))


def write_target(path: str | Path, target: Target) -> None:
    write_atomically(path, target_toml(target))


def write_board(path: str | Path, board: Board) -> None:
    write_atomically(path, board_toml(board))
