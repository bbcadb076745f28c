"""Libraries that some test modules compare against or drive, imported when a test first
uses them rather than when its module is collected.

Each worker of the parallel run collects every test module, so a library imported at the
top of one module is imported by all six workers, whichever of them runs its tests:
scipy.spatial.transform (0.2 s of CPU), scipy.optimize, pinocchio, psycopg and CESAPI
(with requests and websocket) cost each worker about half a second that way. A name
here stands for the module (or the module's name) and imports it at the first attribute
read or call; after that it costs one attribute lookup.
"""

from __future__ import annotations

import importlib
from typing import Any


class Lazy:
    """Module ``module`` (or its attribute ``name``), imported at first use."""

    def __init__(self, module: str, name: str | None = None) -> None:
        self._module = module
        self._name = name

    def _load(self) -> Any:
        found = importlib.import_module(self._module)
        return found if self._name is None else getattr(found, self._name)

    def __getattr__(self, attr: str) -> Any:
        # pytest looks every module-level name over for its marks (``pytestmark``,
        # ``_fixture_function_marker``, …) as it collects: those are not the library's
        if attr.startswith("_") or attr.startswith("pytest"):
            raise AttributeError(attr)
        return getattr(self._load(), attr)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._load()(*args, **kwargs)

    def __repr__(self) -> str:
        return f"Lazy({self._module!r}, {self._name!r})"


Rotation: Any = Lazy("scipy.spatial.transform", "Rotation")
least_squares: Any = Lazy("scipy.optimize", "least_squares")
pinocchio: Any = Lazy("pinocchio")
psycopg: Any = Lazy("psycopg")
