"""Scenes for the independent renderer (:mod:`cellcal.mocks.rig.texture_render`): an oblique
four-camera rig with barrel lenses, ChArUco board poses for calibrating it, a flange target
of mixed marker sizes on tilted faces and its poses, and writing them all in the layout
``cellcal rig calibrate --views`` and ``rig measure --sets`` read. Every builder is
deterministic from its seed. None of it comes from ``mocks/rig/scene.py``: other focal lengths,
lens, board, dictionary and target, so a rig proven here is not proven on its own images.

``python -m cellcal.mocks.rig.texture_render --out DIR`` (or ``-m
cellcal.mocks.rig.texture_scenes``)
writes a whole data set: ``views/``, ``board.toml``, ``true-rig.toml``, ``target.toml``,
``sets/`` and ``truth.json`` (the true board and target poses).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Rig, Target
from cellcal.files.images import write_image
from cellcal.files.photogrammetry import write_board, write_rig, write_target

Array = np.ndarray

#: The test board: 10×7 squares of 40 mm, 30 mm 5×5 markers (cellcal's own is 7×5, 60 mm, 4×4).
TEST_BOARD = Board("DICT_5X5_100", (10, 7), 40.0, 30.0)
#: Image size of the rig's cameras.
SIZE = (1280, 1024)


def _unit(v: Array) -> Array:
    out: Array = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    return out


def _rotation(axis: Array, angle: float) -> Array:
    """Rotation matrix about a unit axis (Rodrigues)."""
    k = _unit(axis)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    out: Array = np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx
    return out


def _frame(z: Array, x_hint: Array) -> Array:
    """Rotation whose z is ``z`` and whose x is ``x_hint`` made perpendicular to it."""
    z = _unit(z)
    x = _unit(x_hint - (x_hint @ z) * z)
    return np.column_stack([x, np.cross(z, x), z])


def _pose(R: Array, t: Array) -> Array:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _perpendicular(v: Array, rng: np.random.Generator) -> Array:
    """A random unit vector perpendicular to ``v``."""
    while True:
        w = rng.standard_normal(3)
        w -= (w @ v) * v / (v @ v)
        if np.linalg.norm(w) > 1e-3:
            return _unit(w)


def oblique_rig(seed: int = 1) -> Rig:
    """Four cameras 1280×1024 (cam0..cam3) on a cone about a common working volume,
    1.1–1.4 m from it, their rays 35–60° apart; fx 1150–1350 px, fy/fx 1.001–1.003,
    principal points 15–45 px off centre, barrel lenses. cam0 is the rig frame."""
    rng = np.random.default_rng([seed, 7001])
    while True:  # the volume's frame: origin at its centre, z away from the cameras
        half = np.radians(rng.uniform(26.0, 30.0))
        az = np.radians(90.0 * np.arange(4) + rng.uniform(-10.0, 10.0, 4))
        dirs = np.column_stack(
            [np.sin(half) * np.cos(az), np.sin(half) * np.sin(az), -np.full(4, np.cos(half))]
        )
        angles = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))[np.triu_indices(4, 1)]
        if angles.min() >= 35.0 and angles.max() <= 60.0:
            break
    poses = []
    for d in dirs:
        centre = d * rng.uniform(1130.0, 1370.0)
        aim = rng.uniform(-20.0, 20.0, 3)
        z = _unit(aim - centre)
        R = _frame(z, np.cross(z, [0.0, 0.0, 1.0])) @ _rotation(
            np.array([0, 0, 1.0]), rng.uniform(-0.4, 0.4)
        )
        poses.append(_pose(R, centre))
    T_cam0_volume = np.linalg.inv(poses[0])
    cameras = []
    for k, T in enumerate(poses):
        fx = rng.uniform(1150.0, 1350.0)
        fy = fx * rng.uniform(1.001, 1.003)
        phi = rng.uniform(0.0, 2 * np.pi)
        off = rng.uniform(15.0, 45.0) * np.array([np.cos(phi), np.sin(phi)])
        cx, cy = (SIZE[0] - 1) / 2 + off[0], (SIZE[1] - 1) / 2 + off[1]
        dist = [rng.uniform(-0.11, -0.07), rng.uniform(0.02, 0.08), *rng.uniform(-3e-4, 3e-4, 2)]
        T_rig_cam = np.eye(4) if k == 0 else T_cam0_volume @ T
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cameras.append(Camera(f"cam{k}", *SIZE, K, np.array([*dist, 0.0]), T_rig_cam))
    return Rig("oblique-rig", tuple(cameras))


def volume_centre(rig: Rig) -> tuple[Array, Array]:
    """The point nearest every camera's optical axis (least squares), and the unit vector
    from it toward the cameras (their mean direction), in the rig frame."""
    A, b, toward = np.zeros((3, 3)), np.zeros(3), np.zeros(3)
    for cam in rig.cameras:
        c, z = cam.T_rig_cam[:3, 3], cam.T_rig_cam[:3, 2]
        P = np.eye(3) - np.outer(z, z)
        A += P
        b += P @ c
    centre = np.linalg.solve(A, b)
    for cam in rig.cameras:
        toward += _unit(cam.T_rig_cam[:3, 3] - centre)
    return centre, _unit(toward)


def _in_image(cam: Camera, px: Array, border: float = 8.0) -> Array:
    ok: Array = (
        (px[:, 0] >= border)
        & (px[:, 0] <= cam.width - 1 - border)
        & (px[:, 1] >= border)
        & (px[:, 1] <= cam.height - 1 - border)
    )
    return ok


def _facing(cam: Camera, point: Array, normal: Array, limit_deg: float) -> bool:
    """Whether the camera sees a face at ``point`` whose outward normal is ``normal``
    (rig frame) at an incidence below ``limit_deg``."""
    to_cam = _unit(cam.T_rig_cam[:3, 3] - point)
    return bool(to_cam @ normal > np.cos(np.radians(limit_deg)))


def board_views(
    rig: Rig, board: Board, n: int, seed: int, max_tilt_deg: float = 65.0
) -> list[Array]:
    """``n`` poses ``T_rig_board`` in the working volume, each seen (90 % of its corners
    inside the image) by at least two cameras, tilted 0 to ``max_tilt_deg`` to one of them
    (about a third beyond 50°) and shown to none more steeply (up to 80°, where it is no
    longer drawn), turned about the normal at random, chosen greedily among candidates to
    cover each camera's image, its corners too."""
    rng = np.random.default_rng([seed, 7002])
    centre, toward = volume_centre(rig)
    across = _frame(-toward, np.array([1.0, 0, 0]))  # columns: lateral, lateral, depth
    nx, ny = board.squares
    size = np.array([nx * board.square, ny * board.square])
    corners = np.asarray(board.cv_board().getChessboardCorners(), dtype=np.float64)
    grid = 4
    covered = np.zeros((len(rig.cameras), grid, grid))
    tilts = max_tilt_deg * ((np.arange(n) + 0.5) / n) ** 0.7
    rng.shuffle(tilts)
    poses: list[Array] = []
    for tilt in np.radians(tilts):
        best, best_score, tries = None, -1.0, 0
        while tries < 4000 and (tries < 60 or best is None):
            tries += 1
            P = centre + across @ (rng.uniform(-1, 1, 3) * [430.0, 360.0, 260.0])
            ref = rig.cameras[int(rng.integers(len(rig.cameras)))]
            u = _unit(ref.T_rig_cam[:3, 3] - P)
            normal = _rotation(_perpendicular(u, rng), tilt) @ u  # toward the viewer
            R = _frame(-normal, _perpendicular(normal, rng))
            T = _pose(R, P - R[:, :2] @ (size / 2))
            pts = corners @ R.T + T[:3, 3]
            hits = np.zeros_like(covered)
            seen, steep = [], False
            for k, cam in enumerate(rig.cameras):
                if not _facing(cam, P, normal, 80.0):  # not drawn
                    continue
                px = cam.project(pts)
                inside = _in_image(cam, px)
                if not _facing(cam, P, normal, max_tilt_deg):
                    steep |= bool(inside.mean() > 0.1)  # shown steeper than max_tilt_deg
                    continue
                if inside.mean() < 0.9:
                    continue
                seen.append(cam.name)
                cell = np.floor(px[inside] / [cam.width, cam.height] * grid).astype(int)
                np.add.at(hits[k], (cell[:, 1].clip(0, 3), cell[:, 0].clip(0, 3)), 1.0)
            if steep or ref.name not in seen or len(seen) < 2:
                continue
            hit = hits >= 3
            score = float((hit / (1.0 + covered)).sum()) + 0.5 * len(seen)
            if score > best_score:
                best, best_score, best_hit = T, score, hit
        if best is None:
            raise RuntimeError("no board pose seen by two cameras: is the board too large?")
        covered += best_hit
        poses.append(best)
    return poses


def plate_target() -> Target:
    """A flange target of six DICT_5X5_100 markers (ids 70–75) of 45, 30 and 20 mm on faces
    tilted 0–35° from the flange axis (z), reference point off every marker centre."""

    def face(x: float, y: float, z: float, tilt_deg: float, toward_deg: float) -> Array:
        a = np.radians(toward_deg)  # the face's normal leans toward this azimuth
        axis = np.array([-np.sin(a), np.cos(a), 0.0])
        R = _rotation(axis, np.radians(tilt_deg)) if tilt_deg else np.eye(3)
        return _pose(R, np.array([x, y, z]))

    markers = (
        Marker(70, 45.0, face(0.0, 0.0, 40.0, 0.0, 0.0)),
        Marker(71, 30.0, face(-72.0, 0.0, 30.0, 25.0, 180.0)),
        Marker(72, 30.0, face(70.0, 6.0, 32.0, 20.0, 0.0)),
        Marker(73, 20.0, face(0.0, 60.0, 28.0, 30.0, 90.0)),
        Marker(74, 20.0, face(4.0, -60.0, 26.0, 15.0, 270.0)),
        Marker(75, 20.0, face(-64.0, -64.0, 22.0, 35.0, 225.0)),
    )
    return Target("flange-plate", "DICT_5X5_100", np.array([14.0, -9.0, 61.0]), markers)


def target_poses(
    rig: Rig, target: Target, n: int, seed: int, max_tilt_deg: float = 30.0
) -> list[Array]:
    """``n`` poses ``T_rig_target`` in the working volume, the target's z toward the
    cameras tilted up to ``max_tilt_deg``, turned about it at random, its largest marker
    whole in the image of at least two cameras (under 60° incidence)."""
    rng = np.random.default_rng([seed, 7003])
    centre, toward = volume_centre(rig)
    across = _frame(-toward, np.array([1.0, 0, 0]))
    big = max(target.markers, key=lambda m: m.size)
    poses: list[Array] = []
    while len(poses) < n:
        z = _rotation(_perpendicular(toward, rng), np.radians(rng.uniform(0, max_tilt_deg)))
        R = _frame(z @ toward, _perpendicular(z @ toward, rng))
        T = _pose(R, centre + across @ (rng.uniform(-1, 1, 3) * [260.0, 220.0, 180.0]))
        T_m = T @ big.T_target_marker
        pts = big.corners() @ T[:3, :3].T + T[:3, 3]
        seen = sum(
            _facing(cam, T_m[:3, 3], T_m[:3, 2], 60.0)
            and bool(_in_image(cam, cam.project(pts), 30).all())
            for cam in rig.cameras
        )
        if seen >= 2:
            poses.append(T)
    return poses


def write_sets(
    directory: str | Path, sets: Sequence[dict[str, Array]], prefix: str = "set"
) -> list[Path]:
    """Each set's images as ``<directory>/<prefix>NNN/<camera>.png`` (NNN from 000); the
    folders written."""
    folders = []
    for k, images in enumerate(sets):
        folder = Path(directory) / f"{prefix}{k:03d}"
        folder.mkdir(parents=True, exist_ok=True)
        for name, img in images.items():
            write_image(folder / f"{name}.png", img)
        folders.append(folder)
    return folders


def write_scene(
    directory: str | Path,
    rig: Rig | None = None,
    board: Board | None = None,
    target: Target | None = None,
) -> None:
    """The scene's files in ``directory``: ``true-rig.toml``, ``board.toml``, ``target.toml``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    if rig is not None:
        write_rig(d / "true-rig.toml", rig)
    if board is not None:
        write_board(d / "board.toml", board)
    if target is not None:
        write_target(d / "target.toml", target)


def main(argv: Sequence[str] | None = None) -> None:
    """Write a data set rendered by the independent renderer (see the module's doc)."""
    from cellcal.mocks.rig.texture_render import (
        Psf,
        RenderParams,
        Sensor,
        render_board,
        render_target,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="folder for the data set (created)")
    ap.add_argument("--views", type=int, default=20, help="board views")
    ap.add_argument("--sets", type=int, default=10, help="target poses (one set each)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--supersample", type=int, default=5)
    ap.add_argument("--disk", type=float, default=0.7, help="defocus disk radius, px")
    ap.add_argument("--sigma", type=float, default=0.5, help="Gaussian blur σ, px")
    ap.add_argument("--noise", type=float, default=2.0, help="noise σ, grey levels")
    ap.add_argument("--prnu", type=float, default=0.0, help="PRNU, relative 1σ")
    ap.add_argument("--max-tilt", type=float, default=65.0, help="board tilt, deg")
    a = ap.parse_args(argv)
    params = RenderParams(
        supersample=a.supersample, psf=Psf(a.disk, a.sigma), sensor=Sensor(a.noise, a.prnu)
    )
    out = Path(a.out)
    rig, board, target = oblique_rig(a.seed), TEST_BOARD, plate_target()
    write_scene(out, rig, board, target)
    views = board_views(rig, board, a.views, a.seed, a.max_tilt)
    write_sets(
        out / "views", [render_board(rig, board, T, params, k) for k, T in enumerate(views)], "view"
    )
    poses = target_poses(rig, target, a.sets, a.seed)
    sets = [render_target(rig, target, T, params, 1000 + k) for k, T in enumerate(poses)]
    write_sets(out / "sets", sets, "set")
    truth = {
        "seed": a.seed,
        "params": repr(params),
        "views": {f"view{k:03d}": T.tolist() for k, T in enumerate(views)},
        "sets": {
            f"set{k:03d}": {
                "T_rig_target": T.tolist(),
                "xyz_mm": (T[:3, :3] @ target.reference + T[:3, 3]).tolist(),
            }
            for k, T in enumerate(poses)
        },
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    print(f"wrote {len(views)} views and {len(poses)} sets to {out}")


if __name__ == "__main__":
    main()
