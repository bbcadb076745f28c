"""In-process simulated devices behind the driver Protocols, reading the simulated cell.

These are the test doubles of the campaign issue: they take time on the clock like the
real thing (motion at the configured joint speed, timed by the twins' motion model
``mocks/motion.py``; sampling at the configured rate) and
refuse what a controller would refuse. The protocol-level mocks that real drivers talk
to over sockets and pseudo-terminals are separate.
"""

from __future__ import annotations

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.clock import Clock
from cellcal.device_options import SimulatedRobotOptions
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription
from cellcal.errors import DeviceError
from cellcal.mocks.motion import JointMove
from cellcal.mocks.simulated_cell import SimulatedCell

SETTLE_S = 0.5


def _cell(context: DeviceContext) -> SimulatedCell:
    if not isinstance(context.cell, SimulatedCell):
        raise DeviceError(
            'driver = "simulated" is the simulated cell: it needs --mock', device=ROBOT_NAME
        )
    return context.cell


class SimulatedRobot:
    def __init__(self, cell: SimulatedCell, clock: Clock, name: str = "simulated-robot") -> None:
        self.cell = cell
        self.clock = clock
        self.name = name
        self.moves = 0

    @classmethod
    def from_options(cls, options: SimulatedRobotOptions, context: DeviceContext) -> SimulatedRobot:
        return cls(_cell(context), context.clock)

    def connect(self) -> None:
        pass

    def move_joints(self, q: Array, speed: float) -> None:
        lo, hi = self.cell.model.limits
        q = np.asarray(q, dtype=np.float64)
        if ((q < lo - 1e-9) | (q > hi + 1e-9)).any():
            raise DeviceError(
                f"{self.name}: target outside the joint limits refused", device=ROBOT_NAME
            )
        move = JointMove(self.cell.q, q, v=self.cell.joint_speed * speed)
        self.clock.sleep(move.duration + SETTLE_S)
        self.cell.set_q(q)
        self.moves += 1

    def actual_joints(self) -> Array:
        return self.cell.q

    def describe(self) -> DeviceDescription:
        """The simulated cell's robot: in-process, no address, nothing to identify."""
        return DeviceDescription(ROBOT_NAME, "simulated")

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass
