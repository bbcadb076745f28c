"""The simulated cell's camera rig and marker target, built from a few numbers.

The bundled mock cell's rig files (``cellcal/data/mock-rig.toml``, ``mock-target.toml``)
were written from these functions, and the benchmark and tests build the same scene:

* four cameras, 1280×1024, f = 1000 px (a 6 mm lens on 6 µm pixels, about the paper's
  cameras), on a 2×2 grid of directions 20° left/right and 15° up/down of the rig's
  axis (rays 30–50° apart), each 1.25 m from the volume's centre and looking at it; the
  rig frame is the first camera's frame (as ``rig calibrate`` makes it);
* a fixture on the flange with five 40 mm ArUco markers (4×4 bits, each on a white
  plate 10 mm wider all round): one facing along the flange's axis, four on a 62 mm
  ring around it tilted 25° outward; the target frame and the reference point are at
  the centre of the middle marker.

Markers are measured while their black border is at least 4 px wide in the image: a
40 mm marker at 1.25 m is 32 px wide (border 5.3 px) face-on and stays measurable to
about 40° of incidence.
"""

from __future__ import annotations

import numpy as np

from cellcal.calib.geometry import Array, invert
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Rig, Target
from cellcal.calib.rotations import matrix_from_euler_xyz

#: Distance from each camera to the centre of the measuring volume, mm.
STANDOFF_MM = 1250.0


def look_at(eye: Array, centre: Array, down: Array) -> Array:
    """``T_world_cam`` of a camera at ``eye`` looking at ``centre`` (OpenCV axes: z to
    the scene, y down the image, along ``down`` as far as it is square to the view)."""
    z = centre - eye
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def _rot_y(deg: float) -> Array:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _rot_x(deg: float) -> Array:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def _camera_poses(standoff_mm: float) -> list[Array]:
    """T_world_cam of the four cameras; the volume centre is at (0, 0, standoff)."""
    centre = np.array([0.0, 0.0, standoff_mm])
    down = np.array([0.0, -1.0, 0.0])
    poses = []
    for el in (20.0, -20.0):
        for az in (-25.0, 25.0):
            eye = centre + _rot_y(az) @ _rot_x(el) @ np.array([0.0, 0.0, -standoff_mm])
            poses.append(look_at(eye, centre, down))
    return poses


def four_camera_rig(
    standoff_mm: float = STANDOFF_MM,
    focal_px: float = 1000.0,
    size: tuple[int, int] = (1280, 1024),
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0),
    name: str = "cell-rig",
) -> Rig:
    """The simulated cell's rig: 4 cameras around a volume ``standoff_mm`` away."""
    w, h = size
    K = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1.0]])
    poses = _camera_poses(standoff_mm)
    T_cam0_world = invert(poses[0])
    return Rig(
        name,
        tuple(
            Camera(f"cam{k}", w, h, K, np.array(dist), T_cam0_world @ T)
            for k, T in enumerate(poses)
        ),
    )


def placed_looking_at(centre: Array, direction: Array, standoff_mm: float = STANDOFF_MM) -> Array:
    """T_base_rig of :func:`four_camera_rig` with its volume centre at ``centre`` (base
    frame, mm), the cameras on the side ``direction`` points to, images upright (the
    image's y toward the base's −z)."""
    centre = np.asarray(centre, dtype=np.float64)
    eye = centre + standoff_mm * np.asarray(direction) / np.linalg.norm(direction)
    T_base_world = look_at(eye, centre, np.array([0.0, 0.0, -1.0]))
    out: Array = T_base_world @ _camera_poses(standoff_mm)[0]
    return out


def volume_centre(rig: Rig, standoff_mm: float = STANDOFF_MM) -> Array:
    """The point all cameras of :func:`four_camera_rig` look at, in the rig frame."""
    T = rig.cameras[0].T_rig_cam
    out: Array = T[:3, :3] @ np.array([0.0, 0.0, standoff_mm]) + T[:3, 3]
    return out


def board_poses(rig: Rig, board: Board, n: int, seed: int, tilt_deg: float = 35.0) -> list[Array]:
    """``n`` poses ``T_rig_board`` of a ChArUco board held in front of the rig, as in a
    calibration capture: facing the rig, tilted up to ±``tilt_deg`` about two axes on a
    spiral, turned ±17° in plane, shifted ±150 mm (±120 mm vertically) about the
    volume's centre."""
    rng = np.random.default_rng(seed)
    centre = volume_centre(rig)
    mean = np.mean([c.T_rig_cam[:3, 3] for c in rig.cameras], axis=0)
    z = (centre - mean) / np.linalg.norm(centre - mean)  # into the board
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R0 = np.column_stack([x, np.cross(z, x), z])
    half = np.array([board.squares[0], board.squares[1], 0.0]) * board.square / 2
    poses = []
    for i in range(n):
        phase = 6.0 * np.pi * i / n + 0.3
        a = np.radians(tilt_deg) * np.sqrt((i + 1) / n) * np.array([np.cos(phase), np.sin(phase)])
        R = R0 @ matrix_from_euler_xyz(np.array([a[0], a[1], rng.uniform(-0.3, 0.3)]))
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ half + rng.uniform([-150, -120, -150], [150, 120, 150])
        poses.append(T)
    return poses


def dome_target(
    marker_mm: float = 40.0,
    ring_mm: float = 62.0,
    tilt_deg: float = 25.0,
    dictionary: str = "DICT_4X4_50",
) -> Target:
    """The flange fixture: a marker facing along the flange's axis (z) at the target
    frame's origin, and four around it on a ring, each face tilted outward, so that
    cameras on every side see several markers squarely."""
    markers = [Marker(0, marker_mm, np.eye(4))]
    for k, az in enumerate((0.0, 90.0, 180.0, 270.0), start=1):
        a = np.radians(az)
        radial = np.array([np.cos(a), np.sin(a), 0.0])
        tangent = np.array([-np.sin(a), np.cos(a), 0.0])
        t = np.radians(tilt_deg)
        z = np.cos(t) * np.array([0.0, 0.0, 1.0]) + np.sin(t) * radial
        x = tangent
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = ring_mm * radial
        markers.append(Marker(k, marker_mm, T))
    return Target("flange-dome", dictionary, np.zeros(3), tuple(markers))
