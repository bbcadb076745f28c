"""What every twin's ``serve`` returns (``cellcal/families.py``): the server, and the
configured device's options pointed at it, so the factory builds the same driver as for
the real device."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from cellcal.mocks.simulated_cell import SimulatedCell

#: Loopback addresses of the twins: trackers and Modbus robots take an ephemeral port
#: each; a simulated UR needs the fixed ports 30004/29999/30003, so each takes the first
#: free address of its range.
TRACKER_HOST = "127.0.0.5"
MODBUS_HOST = "127.0.0.3"
KUKA_HOST = "127.0.0.7"
ABB_HOST = "127.0.0.8"
FANUC_HOST = "127.0.0.11"
YASKAWA_HOST = "127.0.0.12"
UR_HOSTS = tuple(f"127.0.0.{k}" for k in range(100, 140))


class Server(Protocol):
    def stop(self) -> None: ...


@dataclass(frozen=True)
class RunningTwin:
    options: Any
    server: Server

    def stop(self) -> None:
        self.server.stop()


def limits_deg(cell: SimulatedCell) -> list[tuple[float, float]]:
    """The simulated robot's joint limits (deg), as its controller enforces them."""
    lo, hi = cell.model.limits
    return [(math.degrees(a), math.degrees(b)) for a, b in zip(lo, hi, strict=True)]
