"""The ``[robot]`` table of a Modbus robot (``driver = "modbus"``), apart from its
driver: reading, validating and planning a configuration takes these options only, so
it needs no pymodbus; the driver (``drivers/modbus_robot.py``) imports pymodbus, and
building it without pymodbus ends in one line naming the ``modbus`` extra."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers.modbus_map import ModbusMap


class ModbusRobotOptions(RobotOptions):
    """``[robot]`` with ``driver = "modbus"``: ``address`` is host or host:port (502),
    ``[robot.map]`` the controller's handshake map; a move that is not done within
    ``move_timeout_s`` has failed, a heartbeat that does not change for
    ``heartbeat_timeout_s`` during a move is a comms fault, and the status registers are
    read every ``poll_s`` while a move runs."""

    driver: Literal["modbus"] = "modbus"
    map: ModbusMap = Field(default_factory=ModbusMap)
    move_timeout_s: Positive = 60.0
    heartbeat_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    poll_s: Annotated[float, Field(gt=0, le=1)] = 0.01
