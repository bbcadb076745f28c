"""The one exception hierarchy of cellcal.

Every error the program raises on purpose derives from :class:`CellcalError`.
A :class:`UserError` is something the person at the terminal can fix (a bad file,
degenerate geometry, an unreachable device): the CLI prints its message on one line
of stderr and exits with code 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class CellcalError(Exception):
    """Base class of every error cellcal raises on purpose."""


class UserError(CellcalError):
    """Bad input or a condition the user can correct; the CLI exits 2."""


class InputError(UserError):
    """Values that cannot be used: wrong shape, NaN/inf, unknown option."""


class FileFormatError(InputError):
    """A file that cannot be read: missing columns, non-numeric values, bad names."""


class DegenerateGeometryError(UserError):
    """The geometry does not determine the answer (too few, collinear, coincident points)."""


class MirroredCorrespondenceError(DegenerateGeometryError):
    """The correspondence is fitted by a reflection, not by a rotation (left-handed frame)."""


class ConvergenceError(UserError):
    """An iterative solver did not reach its tolerance."""


class MeasurementError(UserError):
    """Data that do not give a measurement: a target seen by too few cameras, images
    that cannot be read, corners that do not fix a pose."""


class DeviceError(UserError):
    """A device that cannot be reached, refuses a command or reports a fault."""


class NoTargetError(DeviceError):
    """The device works but does not measure its target at this pose: a broken beam, a
    target the cameras do not see. The campaign keeps the pose with what the other
    sensors measured, and says so."""


class CampaignError(UserError):
    """A campaign that cannot be started or resumed as asked (unknown id, changed plan)."""


class AcceptanceError(CellcalError):
    """The work was done but its result failed an acceptance check (the target does not
    follow the robot, units that do not fit, corrections beyond manufacturing tolerances,
    no convergence). The CLI prints one line naming the check and exits 3; nothing that
    claims to be a calibrated model is written unless ``--accept`` is given."""

    def __init__(self, check: str, message: str) -> None:
        super().__init__(f"{check}: {message}")
        self.check = check
        self.message = message
