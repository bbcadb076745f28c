"""The optional libraries: which extra of ``pip install "cellcal[…]"`` brings each, and
the one line a missing one ends in.

``pip install cellcal`` is the core: calibration, registration, planning, the laser
tracker over its line protocol, the SQLite store and the command line. A feature beyond
it imports its library only when it is used — inside the function that needs it, or in
a module that only that feature imports — under :func:`needs`, which turns the library's
absence into a :class:`~cellcal.errors.MissingExtraError` (one line, exit 2)::

    cellcal: error: the robot driver "ur" needs ur-rtde: pip install "cellcal[ur]"

The extras themselves are in ``pyproject.toml`` (``[project.optional-dependencies]``);
``tests/test_extras.py`` checks that the two agree.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager

from cellcal.errors import MissingExtraError

#: An optional library's top-level module → (the package on PyPI, the extra that brings it).
PROVIDERS: dict[str, tuple[str, str]] = {
    "rtde_control": ("ur-rtde", "ur"),  # the UR driver
    "rtde_receive": ("ur-rtde", "ur"),
    "pymodbus": ("pymodbus", "modbus"),  # the Modbus robot driver
    "httpx": ("httpx", "abb"),  # the ABB driver (Robot Web Services)
    # the photogrammetry rig: its maths, the opencv and files backends, the twins' images
    "cv2": ("opencv-contrib-python-headless", "opencv"),
    "gi": ("PyGObject", "cameras"),  # the aravis backend (with Debian's Aravis packages)
    "pinocchio": ("pin", "urdf"),  # URDF models: export urdf, --model robot.urdf
    "aiohttp": ("aiohttp", "service"),  # the cell service and its clients
    "matplotlib": ("matplotlib", "report"),  # the campaign report's figures
    "psycopg": ("psycopg", "fleet"),  # the fleet's central PostgreSQL
}


def missing_extra(exc: ImportError, feature: str) -> MissingExtraError | None:
    """The one-line error for ``exc`` when it is an optional library that is not
    installed; ``None`` for any other import error (a bug, a broken installation)."""
    top = (exc.name or "").partition(".")[0]
    if top not in PROVIDERS:
        return None
    return MissingExtraError(feature, *PROVIDERS[top])


@contextmanager
def needs(feature: str) -> Iterator[None]:
    """Imports inside the block that find an optional library missing end in
    :class:`~cellcal.errors.MissingExtraError`: ``{feature} needs {package}: pip install
    "cellcal[{extra}]"``."""
    try:
        yield
    except ImportError as exc:
        missing = missing_extra(exc, feature)
        if missing is None:
            raise
        raise missing from exc


def installed(feature: str, *modules: str) -> None:
    """Refuse now, as :func:`require` would, when an optional library of ``modules`` is
    not installed, without importing it: for a library only a later step uses (the
    service's reports need matplotlib, which takes longer to import than the rest of
    the service's start)."""
    for module in modules:
        if module not in PROVIDERS:
            raise ValueError(f"{module}: not an optional library of cellcal.extras")
        try:
            found = importlib.util.find_spec(module) is not None
        except ImportError:
            found = False
        if not found:
            raise MissingExtraError(feature, *PROVIDERS[module])


def require(feature: str, *modules: str) -> None:
    """Import the optional libraries ``modules`` now (before any work that would be lost
    without them), under :func:`needs`."""
    with needs(feature):
        for module in modules:
            if module not in PROVIDERS:
                raise ValueError(f"{module}: not an optional library of cellcal.extras")
            importlib.import_module(module)
