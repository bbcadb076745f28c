"""The one exception hierarchy of cellcal.

Every error the program raises on purpose derives from :class:`CellcalError`.
A :class:`UserError` is something the person at the terminal can fix (a bad file,
degenerate geometry, an unreachable device): the CLI prints its message on one line
of stderr and exits with code 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


class CellcalError(Exception):
    """Base class of every error cellcal raises on purpose."""


class UserError(CellcalError):
    """Bad input or a condition the user can correct; the CLI exits 2."""


class InputError(UserError):
    """Values that cannot be used: wrong shape, NaN/inf, unknown option."""


class ConfigError(UserError):
    """A configuration file that cannot be used; the message names the key."""


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
    """A device that cannot be reached, refuses a command or reports a fault.

    ``device``: the device's name in the configuration (``"robot"``, a sensor's name),
    when the raiser knows it; the message says the same in words. Every DeviceError a
    driver raises names its device, and the campaign engine names those that reach it
    without one (:func:`device_errors`)."""

    def __init__(self, *args: object, device: str | None = None) -> None:
        super().__init__(*args)
        self.device = device


class NoTargetError(DeviceError):
    """The device works but does not measure its target at this pose: a broken beam, a
    target the cameras do not see. The campaign keeps the pose with what the other
    sensors measured, and says so."""


@contextmanager
def device_errors(device: str) -> Iterator[None]:
    """A DeviceError raised inside that names no device is ``device``'s: it leaves with
    ``.device`` set, the same error with the same message."""
    try:
        yield
    except DeviceError as exc:
        if exc.device is None:
            exc.device = device
        raise


def device_of(exc: BaseException) -> str | None:
    """The device a failure names: the first DeviceError with a ``device`` among the
    error and its causes (``raise … from``, or raised while handling one)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, DeviceError) and e.device is not None:
            return e.device
        e = e.__cause__ or e.__context__
    return None


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


class MissingExtraError(UserError):
    """A feature whose optional library is not installed (``cellcal.extras``): the line
    names the library and the extra that brings it, ``pip install "cellcal[ur]"``."""

    def __init__(self, feature: str, package: str, extra: str) -> None:
        super().__init__(f'{feature} needs {package}: pip install "cellcal[{extra}]"')
        self.feature = feature
        self.package = package
        self.extra = extra
