"""The KR 5 arc's joint limits as the robot twins' tests give them to a controller, and
the controller model the KUKA and ABB twins share (``cellcal/mocks/kuka/krc.py``: a
controller running cellcal's loop), built for the tests."""

from __future__ import annotations

from cellcal.mocks.kuka.krc import KrcController, KrcFaults

#: The KR 5 arc's joint limits (deg), as its controller enforces them.
LIMITS_DEG = [
    (-155.0, 155.0),
    (-180.0, 65.0),
    (-15.0, 158.0),
    (-350.0, 350.0),
    (-130.0, 130.0),
    (-350.0, 350.0),
]


def krc(q0_deg: list[float], *, time_scale: float = 0.0, **faults: object) -> KrcController:
    """A controller at ``q0_deg``, moving at 150 °/s × ``time_scale``, with ``faults``
    (:class:`KrcFaults`' fields)."""
    return KrcController(
        q0_deg=q0_deg,
        limits_deg=LIMITS_DEG,
        joint_speed_deg_s=150.0,
        time_scale=time_scale,
        faults=KrcFaults(**faults),  # type: ignore[arg-type]
    )
