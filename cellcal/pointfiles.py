"""Reading the point CSV files of the public contract (``name,x,y,z`` in mm).

Files are read here, at the edge, and handed to ``cellcal.calib`` as arrays. Every
problem is a :class:`~cellcal.errors.FileFormatError` naming the file and line.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cellcal.errors import FileFormatError, InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class NamedPoints:
    """Points read from a file: ``names`` in file order, ``xyz`` (n×3, mm), and ``sigma``
    (n×3 standard deviations in mm) when the file has ``sx,sy,sz`` columns."""

    path: str
    names: tuple[str, ...]
    xyz: Array
    sigma: Array | None


def _number(text: str, where: str, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FileFormatError(f"{where}: {column} is not a number: {text.strip()!r}") from None
    if not math.isfinite(value):
        raise FileFormatError(f"{where}: {column} is not finite: {text.strip()!r}")
    return value


def read_points(path: str | Path) -> NamedPoints:
    """Read a ``name,x,y,z`` CSV (extra columns ignored; optional ``sx,sy,sz``)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise FileFormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise FileFormatError(f"{p}: is a directory, not a CSV file") from None
    except UnicodeDecodeError:
        raise FileFormatError(f"{p}: not a UTF-8 text file") from None
    except OSError as exc:
        raise FileFormatError(f"{p}: cannot be read ({exc.strerror})") from None
    rows = list(csv.reader(text.splitlines()))
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise FileFormatError(f"{p}: empty file; expected a header name,x,y,z")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in ("name", "x", "y", "z") if c not in header]
    if missing:
        raise FileFormatError(
            f"{p}: header lacks column(s) {', '.join(missing)}; expected name,x,y,z"
        )
    dup_cols = {h for h in header if header.count(h) > 1 and h in ("name", "x", "y", "z")}
    if dup_cols:
        raise FileFormatError(f"{p}: column {sorted(dup_cols)[0]} appears twice in the header")
    col = {h: header.index(h) for h in header}
    has_sigma = all(c in col for c in ("sx", "sy", "sz"))
    names: list[str] = []
    seen: dict[str, int] = {}
    xyz: list[list[float]] = []
    sig: list[list[float]] = []
    lines = [i + 1 for i, line in enumerate(text.splitlines()) if line.strip()]
    for row, lineno in zip(rows[1:], lines[1:], strict=True):
        where = f"{p}:{lineno}"
        if len(row) < len(header):
            raise FileFormatError(f"{where}: {len(row)} fields, the header has {len(header)}")
        name = row[col["name"]].strip()
        if not name:
            raise FileFormatError(f"{where}: empty point name")
        if name in seen:
            raise FileFormatError(f"{where}: point name {name!r} already used on line {seen[name]}")
        seen[name] = lineno
        names.append(name)
        xyz.append([_number(row[col[c]], where, c) for c in ("x", "y", "z")])
        if has_sigma:
            s = [_number(row[col[c]], where, c) for c in ("sx", "sy", "sz")]
            if min(s) <= 0:
                raise FileFormatError(f"{where}: sx, sy, sz must be positive (1σ in mm)")
            sig.append(s)
    if not names:
        raise FileFormatError(f"{p}: no points after the header")
    return NamedPoints(
        path=str(p),
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
