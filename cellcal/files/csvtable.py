"""A strict little CSV reader shared by the contract's file formats.

It reads a header and numeric columns by name, and turns every problem into a
:class:`~cellcal.errors.FileFormatError` that names the file and line: a missing,
unreadable or non-regular file, a missing or repeated column, a row with fewer or more
fields than the header (more: usually a decimal comma), a non-numeric, non-finite or
absurdly large value; a semicolon-delimited file gets a hint.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path

from cellcal.errors import FileFormatError
from cellcal.files.text import read_text

#: No coordinate (mm) or joint reading (deg) of a cell comes near this.
MAX_ABS = 1e7
#: A unit in brackets after a column name, as tracker software exports it: "X [mm]".
_UNIT = re.compile(r"\s*[\[(](mm|deg|°|degrees?|millimet(er|re)s?)[\])]\s*$", re.IGNORECASE)


def _column_name(raw: str) -> str:
    """Header names are case-insensitive, stripped, and may carry their unit in brackets
    (``X [mm]``, ``q1 (deg)``): the unit must be the one the format takes."""
    return _UNIT.sub("", raw.strip()).strip().lower()


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
        if abs(value) > MAX_ABS:
            raise FileFormatError(
                f"{self.where(k)}: {name} = {text} is out of range (|value| ≤ {MAX_ABS:g})"
            )
        return value


def read_table(path: str | Path, required: tuple[str, ...], expected: str) -> Table:
    """Read ``path``; ``required`` columns must be present once each (``expected`` is the
    header to suggest in messages). Blank lines are skipped; a UTF-8 BOM is accepted."""
    p = Path(path)
    text = read_text(p, "a CSV file")
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    parsed: list[list[str]] = []
    numbers: list[int] = []
    start = 1
    try:
        for row in reader:
            if any(c.strip() for c in row):
                parsed.append(row)
                numbers.append(start)
            start = reader.line_num + 1
    except csv.Error as exc:
        raise FileFormatError(f"{p}:{reader.line_num}: not valid CSV ({exc})") from None
    if not parsed:
        raise FileFormatError(f"{p}: empty file; expected a header {expected}")
    if any("\n" in c or "\r" in c for row in parsed for c in row):
        k = next(i for i, row in enumerate(parsed) if any("\n" in c or "\r" in c for c in row))
        raise FileFormatError(f"{p}:{numbers[k]}: a quoted field spans lines")
    header = tuple(_column_name(h) for h in parsed[0])
    missing = [c for c in required if c not in header]
    if missing:
        hint = ""
        if len(header) == 1 and ";" in parsed[0][0]:
            hint = (
                " (the file is semicolon-delimited: cellcal reads comma-separated values "
                "with a decimal point; export as CSV with ',' or convert it)"
            )
        raise FileFormatError(
            f"{p}: header lacks column(s) {', '.join(missing)}; expected {expected}{hint}"
        )
    twice = sorted({h for h in header if h and header.count(h) > 1})
    if twice:
        raise FileFormatError(f"{p}: column {twice[0]} appears twice in the header")
    rows = []
    for lineno, row in zip(numbers[1:], parsed[1:], strict=True):
        if len(row) != len(header):
            hint = " (a decimal comma?)" if len(row) > len(header) else ""
            raise FileFormatError(
                f"{p}:{lineno}: {len(row)} fields, the header has {len(header)}{hint}"
            )
        rows.append(tuple(c.strip() for c in row))
    if not rows:
        raise FileFormatError(f"{p}: no data rows after the header")
    return Table(str(p), header, tuple(rows), tuple(numbers[1:]))
