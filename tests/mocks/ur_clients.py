"""The UR twin and UR's own clients for the tests that drive one with the other: the
bundled UR10e cell's twin (:func:`ur_twin`), ur_rtde's two interfaces (:func:`clients`)
and the waits those tests share."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from importlib import resources
from typing import Any

import numpy as np

from cellcal.config import load_config
from cellcal.files.models import load_model
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.ur.server import CellInURUnits, URTwin


def _ur10e_cell() -> tuple[np.ndarray, SimulatedCell]:
    """The bundled UR10e cell: its home (rad) and the simulated cell, whose nominal model
    is the controller's kinematics."""
    ref = resources.files("cellcal") / "data" / "mock-cell-ur10e.toml"
    with resources.as_file(ref) as path:
        config = load_config(path, relative_paths=False)
    cell = SimulatedCell(config, load_model(config.robot.model).model, seed=1)
    return np.radians(config.robot.home_deg), cell


Q0, CELL = _ur10e_cell()
KIN = CellInURUnits(CELL)
Q1 = Q0 + np.array([0.3, -0.2, 0.25, 0.1, -0.15, 0.4])


@contextlib.contextmanager
def ur_twin(host: str, **kw: object) -> Iterator[URTwin]:
    sim = URTwin(KIN, q0=Q0, **kw)  # type: ignore[arg-type]
    sim.start(host)
    try:
        yield sim
    finally:
        sim.stop()


class Clients:
    """ur_rtde's receive (``r``) and control (``c``) interfaces. ``close()`` drops the
    only references: the destructors disconnect (each sleeps 500 ms, holding the GIL)."""

    def __init__(self, host: str) -> None:
        import rtde_control  # the tests that use it skip where ur_rtde is missing
        import rtde_receive

        self.r: Any = rtde_receive.RTDEReceiveInterface(host)
        self.c: Any = rtde_control.RTDEControlInterface(host)

    def close(self) -> None:
        self.c = None
        self.r = None


@contextlib.contextmanager
def clients(host: str) -> Iterator[Clients]:
    ur = Clients(host)
    try:
        yield ur
    finally:
        ur.close()


def wait_for(cond: Callable[[], bool], what: str, limit: float = 10.0) -> None:
    deadline = time.monotonic() + limit
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.002)


def halted_joints(
    sim: URTwin, ur: Clients, still_s: float = 0.1, limit: float = 10.0
) -> np.ndarray:
    """The joints once the twin's own view and the receive link agree and have not
    changed for ``still_s``: a halted robot's position, not one a cycle before it."""
    deadline = time.monotonic() + limit
    last: np.ndarray | None = None
    since = time.monotonic()
    while True:
        q = np.array(ur.r.getActualQ())
        agreed = np.allclose(sim.q, q, rtol=0, atol=1e-9)
        now = time.monotonic()
        if not agreed or last is None or not np.array_equal(q, last):
            since = now
        elif now - since >= still_s:
            return q
        last = q if agreed else None
        if now > deadline:
            raise AssertionError("timed out waiting for the halted joints")
        time.sleep(0.002)


def eventually(check: Callable[[], None], limit: float = 5.0) -> None:
    """Run an assertion until it holds: the receive connection is independent of the
    control connection and may be a few cycles behind it on a loaded machine."""
    deadline = time.monotonic() + limit
    while True:
        try:
            check()
            return
        except AssertionError:
            if time.monotonic() > deadline:
                raise
        time.sleep(0.002)
