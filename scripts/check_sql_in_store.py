#!/usr/bin/env python3
"""One face for the store: SQL runs only in the store's modules.

Reads every ``*.py`` under the paths given (default: ``cellcal``) with :mod:`ast` and
reports, one line each (``file:line: what``), what runs SQL or opens a database outside
``cellcal/store/*.py``:

* a call of a method named ``execute``, ``executemany`` or ``executescript`` (on a
  connection, a cursor, sqlite-utils' database: whatever the object, the name is the
  store's alone);
* a cursor: a call of a method named ``cursor``, or ``sqlite3.Cursor``;
* a connection opened: ``sqlite3.connect``, ``sqlite_utils.Database`` (also imported by
  name: ``from sqlite3 import connect``);
* a file that does not parse (it cannot be checked).

Exit status: 0 when there is nothing to report, 1 when there is, 2 for a path that does
not exist. Usage: ``python scripts/check_sql_in_store.py [PATH ...]``.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path, PurePath

#: The store's modules: the only ones that may run SQL.
STORE_MODULES = "cellcal/store/*.py"
#: Method names that run SQL, whatever they are called on.
SQL_METHODS = frozenset({"execute", "executemany", "executescript"})
#: Per module, the names that open a database or a cursor.
OPENERS = {
    "sqlite3": frozenset({"connect", "Cursor"}),
    "sqlite_utils": frozenset({"Database"}),
}


def in_store(path: Path) -> bool:
    """Whether ``path`` is one of the store's modules."""
    return PurePath(path.resolve().as_posix()).match(STORE_MODULES)


class _Finder(ast.NodeVisitor):
    def __init__(self) -> None:
        self.found: list[tuple[int, str]] = []
        #: local name → the module it is (``import sqlite3 as db``)
        self.modules: dict[str, str] = {}

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            if alias.name in OPENERS:
                self.modules[alias.asname or alias.name] = alias.name
        self.generic_visit(node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        names = OPENERS.get(node.module or "", frozenset())
        for alias in node.names:
            if alias.name in names:
                self.found.append(
                    (node.lineno, f"imports {node.module}.{alias.name} (opens a database)")
                )
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        func = node.func
        if isinstance(func, ast.Attribute) and func.attr in SQL_METHODS:
            self.found.append((node.lineno, f"{ast.unparse(func)}() runs SQL"))
        elif isinstance(func, ast.Attribute) and func.attr == "cursor":
            self.found.append((node.lineno, f"{ast.unparse(func)}() opens a cursor"))
        self.generic_visit(node)

    def visit_Attribute(self, node: ast.Attribute) -> None:
        if isinstance(node.value, ast.Name):
            module = self.modules.get(node.value.id)
            if module is not None and node.attr in OPENERS[module]:
                self.found.append((node.lineno, f"{ast.unparse(node)} (opens a database)"))
        self.generic_visit(node)


def offences(path: Path) -> list[tuple[int, str]]:
    """What in the module at ``path`` runs SQL or opens a database, by line."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    except (SyntaxError, UnicodeDecodeError, ValueError) as exc:
        line = getattr(exc, "lineno", None) or 1
        return [(line, f"cannot be parsed, so not checked ({type(exc).__name__})")]
    finder = _Finder()
    finder.visit(tree)
    return sorted(finder.found)


def modules(paths: list[Path]) -> Iterator[Path]:
    for path in paths:
        if path.is_dir():
            yield from sorted(p for p in path.rglob("*.py") if p.is_file())
        else:
            yield path


def main(argv: list[str]) -> int:
    paths = [Path(a) for a in argv] or [Path("cellcal")]
    missing = [p for p in paths if not p.exists()]
    if missing:
        for p in missing:
            print(f"{p}: no such file or folder", file=sys.stderr)
        return 2
    n = 0
    for path in modules(paths):
        if in_store(path):
            continue
        for line, what in offences(path):
            print(f"{path}:{line}: {what} outside the store ({STORE_MODULES})")
            n += 1
    return 1 if n else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
