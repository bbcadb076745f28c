"""The result of a calibration: frozen values, display units at the edges.

``cellcal.calib.identification`` produces them; the CLI, the model files, the campaign
analysis and the report read them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.calib.error_model import Groups, ParameterSpec, State, predict
from cellcal.calib.error_terms import Conditions
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import Identifiability
from cellcal.calib.parameter_choice import Choice
from cellcal.calib.robot_model import RobotModel
from cellcal.calib.term_choice import TermChoice


@dataclass(frozen=True)
class ParameterEstimate:
    """A parameter's estimate in display units (mm or deg): for a kinematic parameter
    ``value`` is the correction to nominal (angles wrapped to (−180°, 180°]), for the
    target offset the coordinate itself.
    ``std`` is its standard uncertainty (0 for a parameter left at nominal)."""

    name: str
    kind: str
    joint: int
    unit: str
    identified: bool
    value: float
    std: float
    #: why a parameter is at nominal: "rank" (not identifiable from these poses), "weak"
    #: (the noise hides it), "fixed" (pinned by the user); "" when identified.
    at_nominal: str = ""


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a calibration produced. Lengths mm; ``T_sensor_base`` maps robot-base
    coordinates into the sensor frame. ``rms_before``/``residuals_before`` are those of
    the nominal model with best-fit sensor frame and target offset.

    ``target_offset``, ``target_offset_std``, ``T_sensor_base`` and ``frame_std`` are those
    of the first target and session; with several (``groups``), ``target_offsets`` (T×3),
    ``target_offsets_std``,
    ``frames`` (S×4×4) and ``frames_std`` hold each one's. A 6-DOF fit adds each target's
    orientation on the flange (``tool_rotations``, T×3×3) and the orientation residuals
    (N×3 rotation vectors, rad)."""

    nominal: RobotModel
    calibrated: RobotModel
    target_offset: Array
    target_offset_std: Array
    T_sensor_base: Array
    frame_std: Array  # rotation vector (rad, 3) then translation (mm, 3), of T at its origin
    parameters: tuple[ParameterEstimate, ...]
    identifiability: Identifiability
    n_points: int
    dof: int
    sigma0: float
    residuals: Array
    residuals_before: Array
    evaluations: int
    weighted: bool
    robust: str | None
    warnings: tuple[str, ...]
    #: the acceptance checks that failed and were overridden (``accept=True``)
    accepted_despite: tuple[str, ...] = ()
    groups: Groups | None = None
    target_offsets: Array | None = None
    target_offsets_std: Array | None = None
    frames: Array | None = None
    frames_std: Array | None = None
    target_rotations: Array | None = None
    orientation_residuals: Array | None = None
    #: the a-posteriori covariance σ₀²(JᵀJ)⁻¹ (internal units: mm, rad) of the parameters
    #: ``covariance_specs`` (the identified ones, sensor frames included), and the points
    #: (sensor frame, one per session) the frames' rotations turn about in it
    covariance: Array | None = None
    covariance_specs: tuple[ParameterSpec, ...] = ()
    pivots: Array | None = None
    #: the condition number with every coordinate weighted alike (what ``cellcal plan``
    #: computes before anything is measured); ``condition_number`` is the fit's own,
    #: each coordinate weighted by 1/σ of its measurement
    condition_number_equal_weights: float = float("nan")
    #: how the k-fold held-out error chose among the noise-hidden parameters (None: none
    #: were hidden, or the fit was robust)
    parameter_choice: Choice | None = None
    #: the error terms beyond geometry tried, accepted or not (None: ``--terms geometric``)
    term_choice: TermChoice | None = None

    @property
    def targets(self) -> tuple[str, ...]:
        return self.groups.targets if self.groups is not None else ("",)

    @property
    def sessions(self) -> tuple[str, ...]:
        return self.groups.sessions if self.groups is not None else ("",)

    @property
    def identified(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters if p.identified)

    @property
    def unidentifiable(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters if not p.identified)

    @property
    def condition_number(self) -> float:
        return self.identifiability.condition_number

    @property
    def rms_before(self) -> float:
        return rms(self.residuals_before)

    @property
    def rms_after(self) -> float:
        return rms(self.residuals)

    @property
    def max_after(self) -> float:
        return float(np.max(np.linalg.norm(self.residuals, axis=1)))

    @property
    def state(self) -> State:
        target_offsets = (
            self.target_offsets if self.target_offsets is not None else self.target_offset
        )
        frames = self.frames if self.frames is not None else self.T_sensor_base[None]
        return State(
            self.calibrated,
            target_offsets,
            frames[:, :3, :3],
            frames[:, :3, 3],
            self.pivots if self.pivots is not None else np.zeros((len(frames), 3)),
            self.target_rotations,
        )

    def predict(
        self, q: Array, groups: Groups | None = None, conditions: Conditions | None = None
    ) -> Array:
        """Target positions in the sensor frame (mm) for joint readings ``q`` (rad)
        (of the first target and session, unless ``groups`` says otherwise), at the
        ``conditions`` the model's error terms read."""
        return predict(self.state, q, groups, conditions)


def rms(r: Array) -> float:
    """RMS length of the rows of an N×3 array (mm)."""
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
