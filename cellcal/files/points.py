"""Reading the point CSV files of the public contract (``name,x,y,z`` in mm).

Files are read here, at the edge, and handed to ``cellcal.calib`` as arrays. Every
problem is a :class:`~cellcal.errors.FileFormatError` naming the file and line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cellcal.errors import FileFormatError, InputError
from cellcal.files.csvtable import read_table

Array = NDArray[np.float64]


@dataclass(frozen=True)
class NamedPoints:
    """Points read from a file: ``names`` in file order, ``xyz`` (n×3, mm), and ``sigma``
    (n×3 standard deviations in mm) when the file has ``sx,sy,sz`` columns."""

    path: str
    names: tuple[str, ...]
    xyz: Array
    sigma: Array | None


def read_points(path: str | Path) -> NamedPoints:
    """Read a ``name,x,y,z`` CSV (extra columns ignored; optional ``sx,sy,sz``)."""
    t = read_table(path, ("name", "x", "y", "z"), "name,x,y,z")
    has_sigma = t.has("sx", "sy", "sz")
    names: list[str] = []
    seen: dict[str, int] = {}
    xyz: list[list[float]] = []
    sig: list[list[float]] = []
    for k, row in enumerate(t.rows):
        name = row[t.column("name")]
        if not name:
            raise FileFormatError(f"{t.where(k)}: empty point name")
        if name in seen:
            raise FileFormatError(
                f"{t.where(k)}: point name {name!r} already used on line {seen[name]}"
            )
        seen[name] = t.lines[k]
        names.append(name)
        xyz.append([t.number(k, c) for c in ("x", "y", "z")])
        if has_sigma:
            s = [t.number(k, c) for c in ("sx", "sy", "sz")]
            if min(s) <= 0:
                raise FileFormatError(f"{t.where(k)}: sx, sy, sz must be positive (1σ in mm)")
            sig.append(s)
    return NamedPoints(
        path=t.path,
        names=tuple(names),
        xyz=np.array(xyz, dtype=np.float64),
        sigma=np.array(sig, dtype=np.float64) if has_sigma else None,
    )


@dataclass(frozen=True)
class MatchedPoints:
    """Common points of two files, in the order of the first; ``warnings`` names the rest."""

    names: tuple[str, ...]
    src: Array
    dst: Array
    src_sigma: Array | None
    dst_sigma: Array | None
    warnings: tuple[str, ...]


def match_points(src: NamedPoints, dst: NamedPoints) -> MatchedPoints:
    """Match rows by name. Names in one file only are ignored with a warning; fewer than
    three common names is an error."""
    index = {n: i for i, n in enumerate(dst.names)}
    common = [n for n in src.names if n in index]
    warnings = []
    only_src = [n for n in src.names if n not in index]
    in_src = set(src.names)
    only_dst = [n for n in dst.names if n not in in_src]
    for label, names, path in (("src", only_src, src.path), ("dst", only_dst, dst.path)):
        if names:
            shown = ", ".join(names[:10]) + (" ..." if len(names) > 10 else "")
            warnings.append(f"{len(names)} point(s) only in {label} {path} ignored: {shown}")
    if len(common) < 3:
        raise InputError(
            f"{src.path} and {dst.path} have {len(common)} point name(s) in common; "
            "at least 3 are needed"
        )
    src_index = {n: i for i, n in enumerate(src.names)}
    si = [src_index[n] for n in common]
    di = [index[n] for n in common]
    return MatchedPoints(
        names=tuple(common),
        src=src.xyz[si],
        dst=dst.xyz[di],
        src_sigma=None if src.sigma is None else src.sigma[si],
        dst_sigma=None if dst.sigma is None else dst.sigma[di],
        warnings=tuple(warnings),
    )
