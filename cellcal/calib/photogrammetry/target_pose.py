"""The target's pose from every corner every camera saw, with its uncertainty.

One least-squares problem over all cameras at once: the target's pose ``T_rig_target``
(6 parameters) minimises the reprojection error of every marker corner seen by every
camera, in pixels. No corner needs to be seen twice: each camera constrains the pose
through the target's known geometry, and the cameras' different directions fix the depth
that one camera alone measures poorly.

* Start: each camera's own pose of the target (``solvePnP`` on undistorted points; both
  solutions of a single flat marker), the one that fits all cameras best.
* Refine: Gauss–Newton with the analytic Jacobian.
* Outliers, one at a time with a refit after each: a camera most of whose markers fit
  worse than 3 σ (moved since calibration; while more than ``min_cameras`` remain),
  else the worst marker of one camera beyond 3 σ, else corners beyond 3.7 σ (χ², 2
  degrees of freedom, 0.999); σ is the residuals' robust scale (never below
  :data:`SIGMA_FLOOR_PX`).
* Uncertainty: first order, ``σ̂² (JᵀJ)⁻¹`` with ``σ̂²`` from the residuals: a 6×6
  covariance of (rotation vector in the rig frame, rad; translation, mm), and the 3×3
  covariance of the reference point. It holds when the corners are unbiased and the rig's
  calibration is right; it cannot see a wrong calibration.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array, invert, skew, so3_exp
from cellcal.calib.photogrammetry.camera_rig import Rig, Target
from cellcal.calib.photogrammetry.marker_lines import MarkerCorners
from cellcal.errors import MeasurementError

#: Least robust scale of the corner residuals, px (keeps perfect data from being cut).
SIGMA_FLOOR_PX = 0.02
#: Corner outlier bound in σ (χ² with 2 degrees of freedom at 0.999 is 3.72²).
CORNER_LIMIT = 3.72
#: View outlier bound: a camera's RMS residual beyond this many σ.
VIEW_LIMIT = 3.0
_ITERATIONS = 30
_MAX_DROPS = 8
_KEY = 1 << 20  # (camera, marker) packed into one integer


@dataclass(frozen=True, eq=False)
class TargetPose:
    """The target measured in one set of images (one image per camera)."""

    T_rig_target: Array
    #: 6×6 covariance of (rotation vector in the rig frame, rad; translation, mm)
    cov_pose: Array
    #: the target's reference point in the rig frame, mm, and its 3×3 covariance, mm²
    xyz_mm: Array
    cov_mm2: Array
    cameras: tuple[str, ...]
    markers: int
    corners: int
    reprojection_rms_px: float
    #: the corners' residual scale σ̂ per image coordinate (px) the covariance is built on
    sigma_px: float
    #: what was left out and why, one short phrase each
    dropped: tuple[str, ...]


@dataclass(frozen=True)
class _Obs:
    cam: NDArray[np.int64]  # (n,) camera index per corner
    P: Array  # (n, 3) corner in the target frame
    xy: Array  # (n, 2) measured, normalised
    marker: NDArray[np.int64]  # (n,) marker id
    R_cr: Array  # (n, 3, 3) its camera's rotation from the rig frame ...
    t_cr: Array  # (n, 3) ... and translation
    f: Array  # (n, 2) its camera's focal lengths, px

    def subset(self, keep: Array) -> _Obs:
        return _Obs(*(a[keep] for a in vars(self).values()))


#: Each target's marker corners in its frame, computed once.
_CORNERS: weakref.WeakKeyDictionary[Target, dict[int, Array]] = weakref.WeakKeyDictionary()


def target_corners(target: Target) -> dict[int, Array]:
    """Each marker's corners (4, 3) in the target frame, by id (computed once a target)."""
    corners = _CORNERS.get(target)
    if corners is None:
        corners = _CORNERS[target] = {m.id: m.corners() for m in target.markers}
    return corners


def _observations(
    rig: Rig, target: Target, views: dict[str, list[MarkerCorners]]
) -> tuple[_Obs, list[str]]:
    corners = target_corners(target)
    names = [c.name for c in rig.cameras]
    cam, P, xy, mk = [], [], [], []
    for name, found in views.items():
        ci = names.index(rig.camera(name).name)
        for m in found:
            if m.id not in corners:
                continue
            cam.extend([ci] * 4)
            P.append(corners[m.id])
            xy.append(m.xy)
            mk.extend([m.id] * 4)
    model = _model(rig)
    c = np.array(cam, dtype=np.int64)
    return (
        _Obs(
            c,
            np.concatenate(P) if P else np.zeros((0, 3)),
            np.concatenate(xy) if xy else np.zeros((0, 2)),
            np.array(mk, dtype=np.int64),
            model.R_cr[c],
            model.t_cr[c],
            model.f[c],
        ),
        names,
    )


class _Model:
    """Projection of the target's corners into the cameras, and its Jacobian (one a rig:
    :func:`_model`)."""

    def __init__(self, rig: Rig) -> None:
        T = [invert(c.T_rig_cam) for c in rig.cameras]
        self.R_cr = np.array([t[:3, :3] for t in T])
        self.t_cr = np.array([t[:3, 3] for t in T])
        self.f = np.array([[c.K[0, 0], c.K[1, 1]] for c in rig.cameras])

    def residuals(self, T: Array, o: _Obs, jacobian: bool) -> tuple[Array, Array | None]:
        """Residuals (measured − predicted) in px, (n, 2), and the Jacobian of the
        prediction (n, 2, 6) for the perturbation ``[exp(ω) R, t + δ]``."""
        p = o.P @ T[:3, :3].T + T[:3, 3]
        pc = (o.R_cr @ p[:, :, None])[..., 0] + o.t_cr
        z = pc[:, 2]
        pred = pc[:, :2] / z[:, None]
        r = (o.xy - pred) * o.f
        if not jacobian:
            return r, None
        d_proj = np.zeros((len(z), 2, 3))
        d_proj[:, 0, 0] = 1.0 / z
        d_proj[:, 1, 1] = 1.0 / z
        d_proj[:, :, 2] = -pred / z[:, None]
        d_proj *= o.f[:, :, None]
        a = d_proj @ o.R_cr  # ∂px/∂p_rig (n, 2, 3)
        # ∂p/∂ω = −[R·P]×, so each row a of ∂px/∂p gives a·(−[R·P]×) = (R·P) × a
        v = (p - T[:3, 3])[:, None, :]
        J = np.empty((len(z), 2, 6))
        J[..., 0] = v[..., 1] * a[..., 2] - v[..., 2] * a[..., 1]
        J[..., 1] = v[..., 2] * a[..., 0] - v[..., 0] * a[..., 2]
        J[..., 2] = v[..., 0] * a[..., 1] - v[..., 1] * a[..., 0]
        J[..., 3:] = a
        return r, J


_MODELS: weakref.WeakKeyDictionary[Rig, _Model] = weakref.WeakKeyDictionary()


def _model(rig: Rig) -> _Model:
    model = _MODELS.get(rig)
    if model is None:
        model = _MODELS[rig] = _Model(rig)
    return model


def _refine(model: _Model, T: Array, o: _Obs) -> Array:
    """Gauss–Newton from ``T``, until a step moves the pose by less than 1e-6 rad and
    1e-4 mm (a ten-thousandth of a pixel at the rig's distances; near the solution each
    step is a small fraction of the last, a thousandth on the bundled cell)."""
    T = T.copy()
    for _ in range(_ITERATIONS):
        r, J = model.residuals(T, o, True)
        assert J is not None
        A = J.reshape(-1, 6)
        try:
            step = np.asarray(np.linalg.solve(A.T @ A, A.T @ r.reshape(-1)), dtype=np.float64)
        except np.linalg.LinAlgError:
            step = np.asarray(np.linalg.lstsq(A, r.reshape(-1), rcond=None)[0], dtype=np.float64)
        T[:3, :3] = so3_exp(step[:3]) @ T[:3, :3]
        T[:3, 3] += step[3:]
        if np.abs(step[:3]).max() < 1e-6 and np.abs(step[3:]).max() < 1e-4:
            break
    return T


def _starts(rig: Rig, o: _Obs) -> list[Array]:
    """Each camera's own pose (or poses) of the target, in the rig frame."""
    out = []
    for ci in np.unique(o.cam):
        sel = o.cam == ci
        P, xy = o.P[sel], o.xy[sel]
        planar = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)[2] < 1e-6 * max(
            float(np.abs(P).max()), 1.0
        )
        flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
        ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            P.astype(np.float64), xy.astype(np.float64), np.eye(3), None, flags=flag
        )
        if not ok:
            continue
        for rv, tv in zip(rvecs, tvecs, strict=True):
            T_cam_target = np.eye(4)
            T_cam_target[:3, :3] = cv2.Rodrigues(rv)[0]
            T_cam_target[:3, 3] = tv.ravel()
            out.append(rig.cameras[int(ci)].T_rig_cam @ T_cam_target)
    return out


def _robust_sigma(r: Array) -> float:
    a = np.abs(r).ravel()
    k = len(a) // 2
    part = np.partition(a, [k - 1, k]) if len(a) > 1 else np.concatenate([a, a])
    median = float(part[k]) if len(a) % 2 else 0.5 * float(part[k - 1] + part[k])
    return max(1.4826 * median, SIGMA_FLOOR_PX)


def measure_target(
    rig: Rig,
    target: Target,
    views: dict[str, list[MarkerCorners]],
    *,
    min_cameras: int = 2,
    start: Array | None = None,
) -> TargetPose:
    """The target's pose from the marker corners each camera found (normalised
    coordinates, :func:`~cellcal.calib.photogrammetry.marker_lines.marker_corners`).

    ``start`` (a previous pose) skips the per-camera start. Raises
    :class:`MeasurementError` when fewer than ``min_cameras`` cameras see the target.
    """
    o, names = _observations(rig, target, views)
    seen = sorted(names[i] for i in np.flatnonzero(np.bincount(o.cam, minlength=1)).tolist())
    if len(seen) < min_cameras:
        which = ", ".join(seen) if seen else "none"
        raise MeasurementError(
            f"target {target.name!r} seen by {len(seen)} camera(s) ({which}); "
            f"at least {min_cameras} are needed"
        )
    model = _model(rig)
    candidates = [start] if start is not None else _starts(rig, o)
    # refine the two starts that fit all cameras best (a flat marker's two poses)
    order = list(range(len(candidates)))
    if len(candidates) > 1:
        costs = [float(np.sum(model.residuals(T0, o, False)[0] ** 2)) for T0 in candidates]
        order = np.argsort(np.nan_to_num(costs, nan=np.inf))[:2].tolist()
    best: tuple[float, Array] | None = None
    for T0 in (candidates[i] for i in order):
        T = _refine(model, T0, o)
        r, _ = model.residuals(T, o, False)
        cost = float(np.sum(r**2))
        if math.isfinite(cost) and (best is None or cost < best[0]):
            best = cost, T
    if best is None:
        raise MeasurementError(f"target {target.name!r}: no pose fits the corners found")
    T = best[1]
    T, o, dropped = _drop_outliers(model, T, o, names, min_cameras)
    return _result(model, T, o, names, target, dropped)


def _drop_outliers(
    model: _Model, T: Array, o: _Obs, names: list[str], min_cameras: int
) -> tuple[Array, _Obs, list[str]]:
    """Leave out, one at a time and refitting after each: a camera most of whose markers
    do not fit (a camera moved since calibration), else the worst-fitting marker in one
    camera (a misread or half-hidden marker), else single corners beyond the χ² bound."""
    dropped: list[str] = []
    for _ in range(_MAX_DROPS):
        r, _ = model.residuals(T, o, False)
        sigma = _robust_sigma(r)
        sq = np.sum(r**2, axis=1)
        if float(sq.max(initial=0.0)) <= (CORNER_LIMIT * sigma) ** 2:
            # no corner beyond the bound, so no marker (RMS at most CORNER_LIMIT/√2 σ)
            # and no camera beyond VIEW_LIMIT σ either: nothing to leave out
            break
        # RMS per (camera, marker) and per camera, through one bincount each
        key = o.cam * _KEY + o.marker
        uniq, inv = np.unique(key, return_inverse=True)
        g_rms = np.sqrt(np.bincount(inv, sq) / np.bincount(inv) / 2)
        groups = {
            (int(k // _KEY), int(k % _KEY)): float(v) for k, v in zip(uniq, g_rms, strict=True)
        }
        bad = {g for g, rms in groups.items() if rms > VIEW_LIMIT * sigma}
        cams = np.unique(o.cam)
        keep = np.ones(len(sq), dtype=bool)
        cam_ms = np.bincount(o.cam, sq) / np.maximum(np.bincount(o.cam), 1)
        worst_cam = int(cams[np.argmax(cam_ms[cams])])
        n_bad = sum(1 for g in bad if g[0] == worst_cam)
        n_all = sum(1 for g in groups if g[0] == worst_cam)
        if len(cams) > min_cameras and n_bad * 2 > n_all:
            keep &= o.cam != worst_cam
            rms = math.sqrt(float(cam_ms[worst_cam]) / 2)
            dropped.append(f"{names[int(worst_cam)]}: view RMS {rms:.2f} px")
        elif bad:
            c, m = max(bad, key=lambda g: groups[g])
            keep &= ~((o.cam == c) & (o.marker == m))
            dropped.append(f"{names[c]}: marker {m} RMS {groups[(c, m)]:.2f} px")
        else:
            out = np.sqrt(sq) > CORNER_LIMIT * sigma
            if out.any() and (~out).sum() >= 6:
                keep &= ~out
                for c in np.unique(o.cam[out]):
                    n = int((out & (o.cam == c)).sum())
                    dropped.append(f"{names[int(c)]}: {n} corner(s)")
        if keep.all():
            break
        o = o.subset(keep)
        if len(np.unique(o.cam)) < min_cameras:
            raise MeasurementError(
                f"fewer than {min_cameras} cameras left after leaving out " + "; ".join(dropped)
            )
        T = _refine(model, T, o)
    return T, o, dropped


def _result(
    model: _Model, T: Array, o: _Obs, names: list[str], target: Target, dropped: list[str]
) -> TargetPose:
    r, J = model.residuals(T, o, True)
    assert J is not None
    A = J.reshape(-1, 6)
    n = A.shape[0]
    ssr = float(np.sum(r**2))
    sigma2 = ssr / max(n - 6, 1)
    JtJ = A.T @ A
    w = np.linalg.eigvalsh(JtJ)  # ascending; its condition number is w[-1] / w[0]
    if not w[0] > w[-1] * 1e-14:
        raise MeasurementError(f"target {target.name!r}: the corners do not fix its pose")
    cov = np.asarray(sigma2 * np.linalg.inv(JtJ), dtype=np.float64)
    ref = T[:3, :3] @ target.reference
    J_ref = np.zeros((3, 6))
    J_ref[:, :3] = -skew(ref)
    J_ref[:, 3:] = np.eye(3)
    xyz = ref + T[:3, 3]
    cams = tuple(sorted(names[i] for i in np.unique(o.cam).tolist()))
    return TargetPose(
        T_rig_target=T,
        cov_pose=cov,
        xyz_mm=xyz,
        cov_mm2=J_ref @ cov @ J_ref.T,
        cameras=cams,
        markers=len(np.unique(o.marker)),
        corners=len(o.cam),
        reprojection_rms_px=math.sqrt(ssr / len(o.cam)),
        sigma_px=math.sqrt(sigma2),
        dropped=tuple(dropped),
    )
