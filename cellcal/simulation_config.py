"""The ``[simulation]`` table of a cell configuration (mock mode only): the simulated
cell's ground truth, the faults its twins inject (``[simulation.faults]``) and how the
cell changed after its calibration (``[simulation.change]``) and its errors beyond
geometry (``[simulation.terms]``)."""

from __future__ import annotations

import itertools
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from cellcal.device_options import Seed, Strict, Vec3

#: the simulated arm's temperature at its calibration (°C)
REFERENCE_C = 20.0


class SimulatedFaults(Strict):
    """Faults the twins inject, for soaks (mock mode only; 0: off)."""

    #: every N-th tracker series loses the beam half-way (restored after beam_restore_s)
    tracker_beam_break_every: Annotated[int, Field(ge=0)] = 0
    tracker_beam_restore_s: Annotated[float, Field(ge=0, le=60)] = 0.2
    #: the tracker drops its link after N lines on each connection
    tracker_drop_after_lines: Annotated[int, Field(ge=0)] = 0
    #: an emScon tracker's sensor warms up for this long after its twin starts (s)
    tracker_warmup_s: Annotated[float, Field(ge=0, le=600)] = 0.0
    #: every N-th move command of the robot ends in a protective stop
    robot_protective_stop_every: Annotated[int, Field(ge=0)] = 0


class SimulatedChange(Strict):
    """The simulated cell after its calibration (mock mode only): what a check between
    calibrations should find. ``joint_offset_deg``: added to each joint's θ (one value a
    joint, or none: a joint's zero moved); ``base_shift_mm``: the robot's base moved in the
    cell (the sensors stay); ``link_mm``: a link length changed, by its parameter's name
    (``a2``, ``d4``: mm added); ``thermal_mm_per_c``: the arm's reach (the sum of its link
    lengths) grows this much per °C above the calibration's 20 °C, each link in proportion
    to its length, at the temperature ``temperature_c`` gives: ``[[t_s, c], ...]`` over the
    campaign's clock (s from its start), linear between the points and held beyond them
    (none: 20 °C)."""

    joint_offset_deg: list[Annotated[float, Field(ge=-10, le=10)]] = Field(default_factory=list)
    base_shift_mm: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    link_mm: dict[
        Annotated[str, Field(pattern=r"^[ad][1-9][0-9]?$")], Annotated[float, Field(ge=-50, le=50)]
    ] = Field(default_factory=dict)
    thermal_mm_per_c: Annotated[float, Field(ge=-1, le=1)] = 0.0
    temperature_c: list[
        Annotated[list[Annotated[float, Field(ge=-1e7, le=1e7)]], Field(min_length=2, max_length=2)]
    ] = Field(default_factory=list, max_length=10000)

    @model_validator(mode="after")
    def _profile(self) -> SimulatedChange:
        times = [t for t, _ in self.temperature_c]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError("temperature_c: [t_s, c] points in increasing t_s")
        if any(not -40 <= c <= 100 for _, c in self.temperature_c):
            raise ValueError("temperature_c: each c from -40 to 100 °C")
        return self

    def temperature_at(self, t_s: float) -> float:
        """The simulated arm's temperature (°C) at ``t_s`` of the campaign's clock."""
        if not self.temperature_c:
            return REFERENCE_C
        ts, cs = zip(*self.temperature_c, strict=True)
        return float(np.interp(t_s, ts, cs))


class SimulatedTerms(Strict):
    """Errors beyond geometry the simulated robot has (mock mode only), for the error
    terms to be tested against a known truth. ``harmonics_deg``: per joint, the first and
    second harmonics of its reading added to its angle, ``[sin1, cos1, sin2, cos2]`` (deg;
    none: no joint has any); ``compliance_deg_per_knm``: per joint, how far it yields
    under the gravity torque about it, of the links it carries and of the payload mounted
    (deg per kN·m; the robot model's mass model gives the torque; none: stiff);
    ``ratio_pct``: per joint, a transmission's ratio error: the joint turns ``1 + k/100``
    times its reading (%; none: exact). Thermal drift is ``[simulation.change]
    thermal_mm_per_c`` with its ``temperature_c``."""

    harmonics_deg: list[
        Annotated[list[Annotated[float, Field(ge=-1, le=1)]], Field(min_length=4, max_length=4)]
    ] = Field(default_factory=list, max_length=20)
    compliance_deg_per_knm: list[Annotated[float, Field(ge=0, le=100)]] = Field(
        default_factory=list, max_length=20
    )
    ratio_pct: list[Annotated[float, Field(ge=-5, le=5)]] = Field(
        default_factory=list, max_length=20
    )


class SimulationConfig(Strict):
    """The simulated cell's ground truth (mock mode only). Same seed, same campaign."""

    seed: Seed = 2018
    length_error_mm: Annotated[float, Field(ge=0)] = 0.3
    angle_error_deg: Annotated[float, Field(ge=0)] = 0.03
    tracker_position_mm: Vec3 = Field(default_factory=lambda: [2800.0, -600.0, 300.0])
    tracker_rotation_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 160.0])
    tracker_radial_um: Annotated[float, Field(ge=0)] = 10.0
    tracker_transverse_um_per_m: Annotated[float, Field(ge=0)] = 6.0
    rig_position_mm: Vec3 = Field(default_factory=lambda: [1478.051, 1015.744, 1026.564])
    rig_rotation_deg: Vec3 = Field(default_factory=lambda: [91.234945, -9.586413, -35.837374])
    rig_blur_px: Annotated[float, Field(ge=0, le=10)] = 0.8
    rig_noise_grey: Annotated[float, Field(ge=0, le=50)] = 2.0
    joint_speed_deg_s: Annotated[float, Field(gt=0, le=3600)] = 60.0
    faults: SimulatedFaults = Field(default_factory=SimulatedFaults)
    change: SimulatedChange = Field(default_factory=SimulatedChange)
    terms: SimulatedTerms = Field(default_factory=SimulatedTerms)
