"""What a rig calibration says about itself: which cameras moved while the views were
taken (as opposed to a few noisy corners), and whether the held-out views confirm the
result.

* **A moved camera** shows as whole views shifted: after the bundle, the mean residual
  of that camera's corners in a view stands far outside what the corners' noise allows
  (``|mean| / (σ̂/√n)`` beyond :data:`SHIFT_Z`), and most of the view's corners are
  rejected. One such view is a mismatched view; two or more are a camera that moved
  (or a lens that was touched) between them. Rejected corners scattered over many views,
  with no view shifted as a whole, are noisy detections: they are left out (named when
  they are more than the fraction a moved camera would lose), and the camera is kept.
* **The held-out views** (fitted again with the cameras fixed) must reproject about as
  well as the fitted ones (:data:`HOLDOUT_RMS_FACTOR`) and give the board's known
  lengths to within a limit (mm RMS, the caller's).

Pure numerics over :class:`~cellcal.calib.photogrammetry.bundle.BundleResult`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cellcal.calib.photogrammetry.bundle import BundleResult, Observations

#: A view whose mean residual is this many standard errors from zero is shifted.
SHIFT_Z = 6.0
#: ... and more than this fraction of its corners are rejected.
SHIFT_REJECTED = 0.5
#: Shifted views that make a moved camera (one is a mismatched view).
MOVED_VIEWS = 2
#: Held-out reprojection RMS allowed, in multiples of the fit's.
HOLDOUT_RMS_FACTOR = 2.0


@dataclass(frozen=True)
class CameraDiagnosis:
    """One camera's rejected corners and what they say: ``shifted`` views (names) with
    their mean shift (px), whether the camera ``moved``, and a one-line ``note`` (None
    when nothing was rejected)."""

    name: str
    corners: int
    rejected: int
    shifted: tuple[str, ...]
    shift_px: tuple[float, ...]
    moved: bool
    note: str | None


def diagnose_camera(
    name: str,
    c: int,
    res: BundleResult,
    obs: Observations,
    view_names: Sequence[str],
    max_rejected_fraction: float,
) -> CameraDiagnosis:
    """Camera ``c``'s rejected corners: a moved camera, a mismatched view, or noise."""
    sel = obs.camera == c
    total, rejected = int(sel.sum()), int((sel & ~res.inliers).sum())
    sigma = max(res.sigma_px, 1e-9)
    shifted, shifts = [], []
    for k in np.unique(obs.view[sel]):
        m = sel & (obs.view == k)
        r = res.residuals[m]
        mean = float(np.linalg.norm(r.mean(axis=0)))
        lost = float((~res.inliers[m]).mean())
        if mean / (sigma / np.sqrt(len(r))) > SHIFT_Z and lost > SHIFT_REJECTED:
            shifted.append(view_names[int(k)])
            shifts.append(mean)
    moved = len(shifted) >= MOVED_VIEWS and rejected > max_rejected_fraction * total
    rms_all = float(np.sqrt(np.mean(np.sum(res.residuals[sel] ** 2, axis=1)))) if total else 0.0
    kept = res.residuals[sel & res.inliers]
    rms = float(np.sqrt(np.mean(np.sum(kept**2, axis=1)))) if len(kept) else 0.0
    note = None
    if moved:
        note = (
            f"{name}: views {', '.join(shifted)} are shifted as a whole by "
            f"{min(shifts):.2f}–{max(shifts):.2f} px ({rejected} of {total} corners rejected, "
            f"{rms_all:.2f} px RMS before, {rms:.3f} px after) — the camera moved, or its "
            "lens was touched, while the views were taken"
        )
    elif shifted:
        note = (
            f"{name}: view {', '.join(shifted)} is shifted as a whole by "
            f"{max(shifts):.2f} px and its corners are left out — was the board moving, or "
            "the view's images not taken together?"
        )
    elif rejected > max_rejected_fraction * total:
        note = (
            f"{name}: {rejected} of {total} corners left out as noisy detections, scattered "
            f"over its views ({rms_all:.3f} px RMS before, {rms:.3f} px after; no view "
            "shifted as a whole, so the camera did not move)"
        )
    return CameraDiagnosis(name, total, rejected, tuple(shifted), tuple(shifts), moved, note)


def holdout_failures(
    reprojection_rms_px: float,
    fit_rms_px: float,
    length_rms_mm: float,
    length_max_mm: float,
    max_length_rms_mm: float,
) -> tuple[str, ...]:
    """The held-out check's failures, each one line with its numbers (none: it passed)."""
    out = []
    if reprojection_rms_px > HOLDOUT_RMS_FACTOR * fit_rms_px:
        out.append(
            f"held-out views reproject at {reprojection_rms_px:.3f} px RMS, more than "
            f"{HOLDOUT_RMS_FACTOR:g}× the fit's {fit_rms_px:.3f} px: the calibration does "
            "not carry to views it was not fitted to (too few views, or views that do not "
            "fill the images)"
        )
    if length_rms_mm > max_length_rms_mm:
        out.append(
            f"held-out board lengths are off by {length_rms_mm:.4f} mm RMS (max "
            f"{length_max_mm:.4f} mm), beyond {max_length_rms_mm:g} mm"
        )
    return tuple(out)
