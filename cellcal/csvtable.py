"""A strict little CSV reader shared by the contract's file formats.

It reads a header and numeric columns by name, and turns every problem into a
:class:`~cellcal.errors.FileFormatError` that names the file and line: a missing file,
a missing or repeated column, a short row, a non-numeric or non-finite value.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

from cellcal.errors import FileFormatError


@dataclass(frozen=True)
class Table:
    """A CSV file: ``header`` (lower-case, stripped), ``rows`` (stripped fields) and the
    line number of each row in the file."""

    path: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    lines: tuple[int, ...]

    def column(self, name: str) -> int:
        return self.header.index(name)

    def has(self, *names: str) -> bool:
        return all(n in self.header for n in names)

    def where(self, k: int) -> str:
        return f"{self.path}:{self.lines[k]}"

    def number(self, k: int, name: str) -> float:
        """Row k's value of column ``name`` as a finite float."""
        text = self.rows[k][self.column(name)]
        try:
            value = float(text)
        except ValueError:
            raise FileFormatError(f"{self.where(k)}: {name} is not a number: {text!r}") from None
        if not math.isfinite(value):
            raise FileFormatError(f"{self.where(k)}: {name} is not finite: {text!r}")
        return value


def read_table(path: str | Path, required: tuple[str, ...], expected: str) -> Table:
    """Read ``path``; ``required`` columns must be present once each (``expected`` is the
    header to suggest in messages). Blank lines are skipped; a UTF-8 BOM is accepted."""
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
    numbered = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip()]
    if not numbered:
        raise FileFormatError(f"{p}: empty file; expected a header {expected}")
    try:
        parsed = list(csv.reader([line for _, line in numbered], strict=True))
    except csv.Error as exc:
        raise FileFormatError(f"{p}: not valid CSV ({exc})") from None
    header = tuple(h.strip().lower() for h in parsed[0])
    missing = [c for c in required if c not in header]
    if missing:
        raise FileFormatError(
            f"{p}: header lacks column(s) {', '.join(missing)}; expected {expected}"
        )
    twice = sorted({h for h in header if h and header.count(h) > 1})
    if twice:
        raise FileFormatError(f"{p}: column {twice[0]} appears twice in the header")
    rows = []
    for (lineno, _), row in zip(numbered[1:], parsed[1:], strict=True):
        if len(row) < len(header):
            raise FileFormatError(f"{p}:{lineno}: {len(row)} fields, the header has {len(header)}")
        rows.append(tuple(c.strip() for c in row))
    if not rows:
        raise FileFormatError(f"{p}: no data rows after the header")
    return Table(str(p), header, tuple(rows), tuple(n for n, _ in numbered[1:]))
