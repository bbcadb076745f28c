"""Bundle adjustment of a camera rig on a calibration board (the numerics of
:mod:`cellcal.calib.photogrammetry.rig_calibration`).

Unknowns: each camera's intrinsics ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` (OpenCV's
model; any of them may be held fixed), each camera's pose ``T_rig_cam`` except the
reference camera's (the rig frame is its frame) and each view's board pose
``T_rig_board``. Residuals: the reprojection error of every board corner in every camera
that saw it (px). Rotations are updated on the right, ``R ← R·exp([δ]×)``, so a pose's
rotation uncertainty is about its own axes.

Levenberg–Marquardt with analytic derivatives. The board poses are eliminated from the
normal equations by a Schur complement (they are independent 6×6 blocks), so only the
cameras' reduced system is dense; the same reduced matrix gives the cameras' marginal
covariance ``σ̂²·S⁻¹`` without inverting the full normal matrix.

Also the bundle's starting values (cameras placed one by one from the board poses of
views they share), the rig's triangulation (N-view, linear, on undistorted normalised
coordinates) and the scale-bar check.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.geometry import Array, invert
from cellcal.calib.photogrammetry.camera_rig import Camera, Rig
from cellcal.calib.rotations import matrix_from_rotvec
from cellcal.errors import ConvergenceError, DegenerateGeometryError, MeasurementError

#: The intrinsic parameters, in the order of the parameter vector.
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Median of the norm of a 2-D standard normal vector, to estimate σ from residual norms.
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))

Index = NDArray[np.int64]
Mask = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Observations:
    """Board corners seen by cameras: ``camera`` and ``view`` indices (m,), the corner
    in board coordinates ``points`` (m, 3), mm, and where it was seen ``pixels`` (m, 2)."""

    camera: Index
    view: Index
    points: Array
    pixels: Array

    def subset(self, keep: Mask) -> Observations:
        return Observations(
            self.camera[keep], self.view[keep], self.points[keep], self.pixels[keep]
        )


@dataclass(frozen=True, eq=False)
class RigState:
    """The unknowns: ``intrinsics`` (C, 9) in :data:`INTRINSICS` order, camera poses
    ``R_rig_cam`` (C, 3, 3) and positions ``p_rig_cam`` (C, 3), board poses
    ``R_rig_board`` (V, 3, 3) and ``t_rig_board`` (V, 3)."""

    intrinsics: Array
    R_rig_cam: Array
    p_rig_cam: Array
    R_rig_board: Array
    t_rig_board: Array


@dataclass(frozen=True, eq=False)
class BundleResult:
    """A solved bundle: the state, which observations were kept (``inliers``), the
    residuals of all observations (m, 2) px, σ̂ per axis (px) and the cameras' covariance
    (C, 15, 15): intrinsics (9, zero where fixed), rotation (3, rad, about the camera's
    axes), position (3, mm, rig frame); zero for the reference camera's pose."""

    state: RigState
    inliers: Mask
    residuals: Array
    sigma_px: float
    camera_cov: Array
    iterations: int


def _skew(v: Array) -> Array:
    """Skew matrices (m, 3, 3) of vectors (m, 3)."""
    z = np.zeros(len(v))
    x, y, w = v[:, 0], v[:, 1], v[:, 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], axis=1).reshape(-1, 3, 3)


def project(state: RigState, obs: Observations) -> tuple[Array, Array, Array, Array]:
    """Pixels (m, 2) of the observations' corners and their derivatives (m, 2, k): by the
    intrinsics (k = 9), by the camera pose (k = 6: rotation, position) and by the board
    pose (k = 6: rotation, translation)."""
    cam, view, P = obs.camera, obs.view, obs.points
    Rb, Rc = state.R_rig_board[view], state.R_rig_cam[cam]
    X_rig = np.einsum("mij,mj->mi", Rb, P) + state.t_rig_board[view]
    X = np.einsum("mji,mj->mi", Rc, X_rig - state.p_rig_cam[cam])
    Z = X[:, 2]
    x, y = X[:, 0] / Z, X[:, 1] / Z
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = state.intrinsics[cam].T
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r²
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    m = len(x)
    J_in = np.zeros((m, 2, 9))
    J_in[:, 0, 0], J_in[:, 1, 1] = xd, yd
    J_in[:, 0, 2], J_in[:, 1, 3] = 1.0, 1.0
    J_in[:, 0, 4], J_in[:, 1, 4] = fx * x * r2, fy * y * r2
    J_in[:, 0, 5], J_in[:, 1, 5] = fx * x * r2 * r2, fy * y * r2 * r2
    J_in[:, 0, 6], J_in[:, 1, 6] = fx * 2.0 * x * y, fy * (r2 + 2.0 * y * y)
    J_in[:, 0, 7], J_in[:, 1, 7] = fx * (r2 + 2.0 * x * x), fy * 2.0 * x * y
    J_in[:, 0, 8], J_in[:, 1, 8] = fx * x * r2**3, fy * y * r2**3
    # d(uv)/d(x, y), then d(x, y)/dX
    D = np.empty((m, 2, 2))
    D[:, 0, 0] = fx * (radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x)
    D[:, 0, 1] = fx * (2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[:, 1, 0] = fy * (2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y)
    D[:, 1, 1] = fy * (radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x)
    G = np.zeros((m, 2, 3))
    G[:, 0, 0] = G[:, 1, 1] = 1.0 / Z
    G[:, 0, 2], G[:, 1, 2] = -x / Z, -y / Z
    A = D @ G  # d(uv)/dX_cam
    RcT = np.transpose(Rc, (0, 2, 1))
    J_cam = np.concatenate([A @ _skew(X), -A @ RcT], axis=2)
    ARcT = A @ RcT
    J_board = np.concatenate([-ARcT @ Rb @ _skew(P), ARcT], axis=2)
    return uv, J_in, J_cam, J_board


def _exp(w: Array) -> Array:
    out: Array = matrix_from_rotvec(w).reshape(-1, 3, 3)
    return out


class _Layout:
    """Where each unknown sits in the parameter vector: the cameras' block (free
    intrinsics, then the pose of every camera but the reference) before the boards'."""

    def __init__(self, n_cams: int, n_views: int, free: Mask, fix_cameras: bool) -> None:
        self.free = np.flatnonzero(free) if not fix_cameras else np.zeros(0, dtype=np.int64)
        nf = len(self.free)
        self.fix_cameras = fix_cameras
        self.n_cams, self.n_views = n_cams, n_views
        self.per_cam = 0 if fix_cameras else nf + 6
        self.nc = 0 if fix_cameras else n_cams * self.per_cam - 6
        self.n = self.nc + 6 * n_views

    def camera_columns(self, c: int) -> tuple[Index, Index]:
        """Columns of camera c's free intrinsics and of its pose (empty for camera 0)."""
        if self.fix_cameras:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        nf = len(self.free)
        if c == 0:
            return np.arange(nf), np.zeros(0, np.int64)
        start = nf + (c - 1) * self.per_cam
        return np.arange(start, start + nf), np.arange(start + nf, start + nf + 6)


def _normal_equations(
    layout: _Layout, obs: Observations, r: Array, J_in: Array, J_cam: Array, J_board: Array
) -> tuple[Array, Array, Array, Array, Array]:
    """H_cc (nc, nc), H_cb (nc, V, 6), H_bb blocks (V, 6, 6), g_c (nc,), g_b (V, 6)."""
    V, nc = layout.n_views, layout.nc
    H_bb = np.zeros((V, 6, 6))
    np.add.at(H_bb, obs.view, np.einsum("mki,mkj->mij", J_board, J_board))
    g_b = np.zeros((V, 6))
    np.add.at(g_b, obs.view, np.einsum("mki,mk->mi", J_board, r))
    H_cc, H_cb, g_c = np.zeros((nc, nc)), np.zeros((nc, V, 6)), np.zeros(nc)
    if nc:
        for c in range(layout.n_cams):
            sel = obs.camera == c
            ci, cp = layout.camera_columns(c)
            cols = np.concatenate([ci, cp])
            Jc = np.concatenate([J_in[sel][:, :, layout.free], J_cam[sel][:, :, : len(cp)]], axis=2)
            H_cc[np.ix_(cols, cols)] += np.einsum("mki,mkj->ij", Jc, Jc)
            g_c[cols] += np.einsum("mki,mk->i", Jc, r[sel])
            cross = np.einsum("mki,mkj->mij", Jc, J_board[sel])
            block = np.zeros((V, len(cols), 6))
            np.add.at(block, obs.view[sel], cross)
            H_cb[cols] += np.transpose(block, (1, 0, 2))
    return H_cc, H_cb, H_bb, g_c, g_b


def _reduced(H_cc: Array, H_cb: Array, Cinv: Array) -> tuple[Array, Array]:
    """The Schur complement S = H_cc − H_cb·C⁻¹·H_bc and H_cb·C⁻¹ (nc, V, 6)."""
    WC = np.einsum("pvi,vij->pvj", H_cb, Cinv)
    nc = H_cc.shape[0]
    S = H_cc - WC.reshape(nc, -1) @ H_cb.reshape(nc, -1).T
    return S, WC


def _inv_blocks(H_bb: Array) -> Array:
    try:
        out: Array = np.asarray(np.linalg.inv(H_bb), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise MeasurementError("a board pose is not fixed by its corners") from None
    return out


def _step(layout: _Layout, state: RigState, dc: Array, db: Array) -> RigState:
    intr, Rc, pc = state.intrinsics.copy(), state.R_rig_cam.copy(), state.p_rig_cam.copy()
    if layout.nc:
        for c in range(layout.n_cams):
            ci, cp = layout.camera_columns(c)
            intr[c, layout.free] += dc[ci]
            if len(cp):
                Rc[c] = Rc[c] @ _exp(dc[cp[:3]][None])[0]
                pc[c] += dc[cp[3:]]
    Rb = state.R_rig_board @ _exp(db[:, :3])
    return RigState(intr, Rc, pc, Rb, state.t_rig_board + db[:, 3:])


def _solve(
    layout: _Layout, state: RigState, obs: Observations, max_iter: int = 100
) -> tuple[RigState, int]:
    """Levenberg–Marquardt from ``state``; returns the state and the iterations done."""
    lam = 1e-3
    uv, J_in, J_cam, J_board = project(state, obs)
    r = (uv - obs.pixels).ravel()
    cost = float(r @ r)
    for it in range(1, max_iter + 1):
        H_cc, H_cb, H_bb, g_c, g_b = _normal_equations(
            layout, obs, r.reshape(-1, 2), J_in, J_cam, J_board
        )
        while True:
            Hb = H_bb + lam * np.einsum("vii->vi", H_bb)[:, :, None] * np.eye(6)
            Cinv = _inv_blocks(Hb + 1e-12 * np.eye(6))
            dc = np.zeros(layout.nc)
            if layout.nc:
                Hc = H_cc + lam * np.diag(np.diag(H_cc))
                S, WC = _reduced(Hc, H_cb, Cinv)
                rhs = -g_c + WC.reshape(layout.nc, -1) @ g_b.ravel()
                try:
                    dc = np.asarray(np.linalg.solve(S, rhs), dtype=np.float64)
                except np.linalg.LinAlgError:
                    raise MeasurementError(
                        "the cameras are not determined by the views (singular bundle)"
                    ) from None
            db = np.einsum("vij,vj->vi", Cinv, -g_b - np.einsum("pvi,p->vi", H_cb, dc))
            trial = _step(layout, state, dc, db)
            uv_t, Ji_t, Jc_t, Jb_t = project(trial, obs)
            r_t = (uv_t - obs.pixels).ravel()
            cost_t = float(r_t @ r_t)
            if np.isfinite(cost_t) and cost_t <= cost:
                break
            lam *= 4.0
            if lam > 1e12:
                return state, it
        done = cost - cost_t <= 1e-12 * cost + 1e-14
        state, cost, r = trial, cost_t, r_t
        J_in, J_cam, J_board = Ji_t, Jc_t, Jb_t
        lam = max(lam / 3.0, 1e-9)
        if done:
            return state, it
    raise ConvergenceError(f"the bundle adjustment did not converge in {max_iter} iterations")


def _covariance(layout: _Layout, state: RigState, obs: Observations, sigma: float) -> Array:
    """The cameras' marginal covariance (C, 15, 15) from σ̂²·S⁻¹ at the solution."""
    C = layout.n_cams
    cov = np.zeros((C, 15, 15))
    if not layout.nc:
        return cov
    uv, J_in, J_cam, J_board = project(state, obs)
    r = uv - obs.pixels
    H_cc, H_cb, H_bb, _, _ = _normal_equations(layout, obs, r, J_in, J_cam, J_board)
    S, _ = _reduced(H_cc, H_cb, _inv_blocks(H_bb))
    try:
        S_inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        raise MeasurementError(
            "the cameras are not determined by the views (singular bundle)"
        ) from None
    for c in range(C):
        ci, cp = layout.camera_columns(c)
        dst = np.concatenate([layout.free, 9 + np.arange(len(cp))])
        src = np.concatenate([ci, cp])
        cov[c][np.ix_(dst, dst)] = sigma**2 * S_inv[np.ix_(src, src)]
    return cov


def adjust(
    state: RigState,
    obs: Observations,
    free: Mask,
    fix_cameras: bool = False,
    outlier_sigma: float = 4.0,
    rounds: int = 6,
) -> BundleResult:
    """Solve the bundle from ``state``, drop corners whose reprojection error exceeds
    ``outlier_sigma``·σ̂ (σ̂ from the median error, so outliers do not inflate it) and
    solve again until the kept set settles. ``free`` (9,) marks the intrinsics that are
    adjusted; with ``fix_cameras`` only the board poses are."""
    n_cams, n_views = state.intrinsics.shape[0], state.t_rig_board.shape[0]
    layout = _Layout(n_cams, n_views, np.asarray(free, dtype=bool), fix_cameras)
    keep = np.ones(len(obs.camera), dtype=bool)
    iterations = 0
    _check_views(obs, n_views)
    for _ in range(rounds):
        state, it = _solve(layout, state, obs.subset(keep))
        iterations += it
        res = project(state, obs)[0] - obs.pixels
        norm = np.hypot(res[:, 0], res[:, 1])
        sigma = max(float(np.median(norm[keep])) / _RAYLEIGH_MEDIAN, 1e-6)
        new = norm <= outlier_sigma * sigma
        # a view left with too few corners for its pose keeps them all
        short = np.bincount(obs.view[new], minlength=n_views) < 3
        new |= short[obs.view]
        if np.array_equal(new, keep):
            break
        keep = new
    kept = obs.subset(keep)
    dof = 2 * int(keep.sum()) - layout.n
    if dof <= 0:
        raise MeasurementError("too few corners for the unknowns of the bundle adjustment")
    sigma_hat = float(np.sqrt(np.sum(res[keep] ** 2) / dof))
    cov = _covariance(layout, state, kept, sigma_hat)
    return BundleResult(state, keep, res, sigma_hat, cov, iterations)


def _check_views(obs: Observations, n_views: int) -> None:
    counts = np.bincount(obs.view, minlength=n_views)
    if (counts < 3).any():
        raise MeasurementError("a view has fewer than 3 corners to fix the board's pose")


# --- starting values -----------------------------------------------------------------------------


def pose(rvec: Any, tvec: Any) -> Array:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).ravel()
    return T


def medoid(poses: list[Array]) -> Array:
    """The pose closest to all others (position mm + rotation as mm at 1 m)."""
    if len(poses) == 1:
        return poses[0]
    P = np.array(poses)
    dp = np.linalg.norm(P[:, None, :3, 3] - P[None, :, :3, 3], axis=2)
    dr = np.linalg.norm(P[:, None, :3, :3] - P[None, :, :3, :3], axis=(2, 3))
    return poses[int(np.argmin((dp + 1000.0 * dr).sum(axis=1)))]


def place_cameras(names: list[str], T_cam_board: dict[tuple[int, str], Array]) -> list[Array]:
    """``T_rig_cam`` of every camera, the first at identity, each next one from the views
    it shares with cameras already placed."""
    placed: dict[str, Array] = {names[0]: np.eye(4)}
    views = {n: {v for (v, c) in T_cam_board if c == n} for n in names}
    while len(placed) < len(names):
        best, shared = None, 0
        for n in names:
            if n not in placed:
                k = sum(len(views[n] & views[p]) for p in placed)
                if k > shared:
                    best, shared = n, k
        if best is None:
            lost = next(n for n in names if n not in placed)
            raise DegenerateGeometryError(
                f"{lost}: never sees the board in a view together with the other cameras "
                "— it cannot be placed in the rig"
            )
        estimates = [
            placed[p] @ T_cam_board[(v, p)] @ invert(T_cam_board[(v, best)])
            for p in placed
            for v in sorted(views[best] & views[p])
        ]
        placed[best] = medoid(estimates)
    return [placed[n] for n in names]


@dataclass(frozen=True, eq=False)
class ScaleBar:
    """Two points of known distance (mm), each seen by at least two cameras:
    camera name → pixel position (u, v)."""

    pixels_a: Mapping[str, Sequence[float]]
    pixels_b: Mapping[str, Sequence[float]]
    length_mm: float


@dataclass(frozen=True)
class ScaleCheck:
    """A known length measured with the calibrated rig: ``ratio`` = measured / known."""

    measured_mm: float
    known_mm: float
    ratio: float


# --- triangulation -------------------------------------------------------------------------


def triangulate(cameras: Sequence[Camera], pixels: Sequence[Array]) -> Array:
    """The point (3,) in the rig frame that the cameras see at ``pixels`` ((2,) each):
    linear N-view triangulation on undistorted normalised coordinates."""
    if len(cameras) < 2:
        raise MeasurementError("a point must be seen by at least two cameras")
    rows = []
    for cam, px in zip(cameras, pixels, strict=True):
        x, y = cam.normalised(np.asarray(px, dtype=np.float64).reshape(1, 2))[0]
        P = invert(cam.T_rig_cam)[:3]
        rows += [x * P[2] - P[0], y * P[2] - P[1]]
    X = np.linalg.svd(np.array(rows))[2][-1]
    if abs(X[3]) < 1e-12:
        raise DegenerateGeometryError("the rays to the point are parallel")
    out: Array = X[:3] / X[3]
    return out


def scale_check(rig: Rig, bar: ScaleBar) -> ScaleCheck:
    """The scale bar's length measured with ``rig``, against its known length."""
    ends = []
    for pixels in (bar.pixels_a, bar.pixels_b):
        names = sorted(pixels)
        ends.append(
            triangulate([rig.camera(n) for n in names], [np.asarray(pixels[n]) for n in names])
        )
    measured = float(np.linalg.norm(ends[1] - ends[0]))
    return ScaleCheck(measured, float(bar.length_mm), measured / float(bar.length_mm))
