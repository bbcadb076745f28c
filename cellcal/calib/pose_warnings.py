"""What a calibration warns of in its poses: a target offset they do not determine, and
targets that lie on one surface."""

from __future__ import annotations

import math

import numpy as np

from cellcal.calib.error_model import ParameterSpec
from cellcal.calib.geometry import Array
from cellcal.calib.identifiability import Identifiability


def pose_warnings(
    ident: Identifiability, specs: tuple[ParameterSpec, ...], sel: tuple[ParameterSpec, ...]
) -> list[str]:
    """Warnings for target-offset components the fit left at nominal: not identifiable
    (the flange orientation never changes) or hidden by the noise."""
    out = []
    lost = [i for i, s in enumerate(specs) if s.kind == "target_offset" and s not in sel]
    rank = [specs[i].name for i in lost if ident.reason(i) == "rank"]
    hidden = [specs[i].name for i in lost if ident.reason(i) == "weak"]
    if rank:
        out.append(
            f"the target offset ({', '.join(rank)}) is not identifiable from these poses "
            "(does the flange orientation never change?); it stays at its nominal value and "
            "the model holds only at the measured orientations"
        )
    if hidden:
        out.append(
            f"the target offset ({', '.join(hidden)}) is hidden by the noise at these poses "
            "(its uncertainty exceeds 1 mm: the flange orientation varies too little); it "
            "stays at its nominal value — vary the wrist orientation more"
        )
    return out


#: Targets whose spread off their best-fit plane is below this fraction of their spread
#: along it lie on a surface.
SURFACE_RATIO = 0.05


def on_a_surface(points: Array) -> str | None:
    """A warning when the targets (N×3, one frame) lie near one plane, else None: a model
    fitted to a surface may predict worse than nominal away from it (a real UR5's
    surface session: 3.0 mm held-out against the nominal model's 1.3 mm)."""
    if len(points) < 4:
        return None
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False) / math.sqrt(len(points))
    if not s[2] < SURFACE_RATIO * s[0]:
        return None
    return (
        f"the targets lie near one surface ({s[2]:.2g} mm RMS off a plane, "
        f"{s[0]:.0f} × {s[1]:.0f} mm RMS along it): the model is fitted to that surface and "
        "may predict worse than nominal away from it — validate off it (--validate) or "
        "spread the poses over a volume"
    )
