"""Photogrammetry files (rig, target, board) and the camera model they describe."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cellcal.calib.geometry import so3_exp
from cellcal.calib.photogrammetry.camera_rig import Board, Camera, Marker, Rig
from cellcal.errors import FileFormatError, InputError
from cellcal.files.photogrammetry import (
    read_board,
    read_rig,
    read_target,
    rig_toml,
    write_board,
    write_rig,
    write_target,
)

# The contract's examples (docs/file-formats.md), the elided matrices filled in.
RIG = """\
name = "cell-rig"
[[camera]]
name = "cam0"
width = 1280
height = 1024
K = [[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]]
dist = [0.0, 0.0, 0.0, 0.0, 0.0]
T_rig_cam = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
# optional: reprojection_rms_px, and the calibration's uncertainties
"""

TARGET = """\
name = "flange-cube"
dictionary = "DICT_4X4_50"      # any cv2.aruco predefined dictionary name
reference = [0.0, 0.0, 0.0]     # the point reported as the measurement, in the target frame
[[marker]]
id = 7
size = 40.0                     # edge of the black square
T_target_marker = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                   [0.0, 0.0, 1.0, 30.0], [0.0, 0.0, 0.0, 1.0]]
[[marker]]
id = 8
size = 40.0
T_target_marker = [[0.0, 0.0, 1.0, 30.0], [0.0, 1.0, 0.0, 0.0],
                   [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
"""

BOARD = """\
dictionary = "DICT_5X5_100"
squares = [7, 5]
square = 30.0
marker = 22.0
legacy = false
"""


def _pose(rotvec: list[float], t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array(rotvec))
    T[:3, 3] = t
    return T


def _camera(name: str = "cam", dist: list[float] | None = None) -> Camera:
    K = np.array([[1012.5, 0.0, 641.25], [0.0, 1008.75, 509.5], [0.0, 0.0, 1.0]])
    return Camera(
        name,
        1280,
        1024,
        K,
        np.array(dist if dist is not None else [0.0] * 5),
        _pose([0.1, -0.3, 0.05], [120.0, -45.5, 30.25]),
        0.12,
    )


def _write(tmp_path: Path, text: str, name: str = "f.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# --- the contract's examples and round trips ---------------------------------------------


def test_contract_examples_parse(tmp_path: Path) -> None:
    rig = read_rig(_write(tmp_path, RIG))
    assert rig.name == "cell-rig" and [c.name for c in rig.cameras] == ["cam0"]
    cam = rig.camera("cam0")
    assert (cam.width, cam.height, cam.K[0, 2], cam.reprojection_rms_px) == (
        1280,
        1024,
        639.5,
        None,
    )
    target = read_target(_write(tmp_path, TARGET))
    assert target.dictionary == "DICT_4X4_50" and [m.id for m in target.markers] == [7, 8]
    np.testing.assert_array_equal(target.reference, [0.0, 0.0, 0.0])
    board = read_board(_write(tmp_path, BOARD))
    assert (board.squares, board.square, board.marker, board.legacy) == ((7, 5), 30.0, 22.0, False)


def _same_camera(a: Camera, b: Camera) -> None:
    assert (a.name, a.width, a.height, a.reprojection_rms_px) == (
        b.name,
        b.width,
        b.height,
        b.reprojection_rms_px,
    )
    for x, y in ((a.K, b.K), (a.dist, b.dist), (a.T_rig_cam, b.T_rig_cam)):
        np.testing.assert_array_equal(x, y)


def test_rig_round_trip_of_four_cameras(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cameras = []
    for k, n in enumerate((5, 8, 12, 14)):
        K = np.array(
            [[1000 + rng.normal(), 0.0, 639.5 + rng.normal()], [0, 1001.3, 511.7], [0, 0, 1]]
        )
        T = _pose(list(rng.normal(size=3)), list(rng.normal(scale=1000.0, size=3)))
        rms = None if k == 2 else float(rng.uniform(0.05, 0.3))
        cameras.append(Camera(f"cam{k}", 1280, 1024, K, rng.normal(scale=0.01, size=n), T, rms))
    rig = Rig("cell-rig", tuple(cameras))
    path = tmp_path / "rig.toml"
    write_rig(path, rig)
    back = read_rig(path)
    assert back.name == rig.name and len(back.cameras) == 4
    for a, b in zip(rig.cameras, back.cameras, strict=True):
        _same_camera(a, b)
    assert rig_toml(back) == path.read_text(encoding="utf-8")
    # the contract's layout: one [[camera]] table each, matrices on one line
    text = path.read_text(encoding="utf-8")
    assert text.count("[[camera]]") == 4 and "K = [[" in text


def test_target_and_board_round_trip(tmp_path: Path) -> None:
    target = read_target(_write(tmp_path, TARGET))
    write_target(tmp_path / "t.toml", target)
    back = read_target(tmp_path / "t.toml")
    assert (back.name, back.dictionary) == (target.name, target.dictionary)
    for a, b in zip(target.markers, back.markers, strict=True):
        assert (a.id, a.size) == (b.id, b.size)
        np.testing.assert_array_equal(a.T_target_marker, b.T_target_marker)
    board = read_board(_write(tmp_path, BOARD))
    write_board(tmp_path / "b.toml", board)
    again = read_board(tmp_path / "b.toml")
    assert (again.dictionary, again.squares, again.square, again.marker, again.legacy) == (
        board.dictionary,
        board.squares,
        board.square,
        board.marker,
        board.legacy,
    )


# --- refusals: one line naming the file and the key --------------------------------------

NOT_RIGID = (
    "[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.01, 0.0], [0.0, 0.0, 0.0, 1.0]]"
)
IDENTITY = (
    "[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]"
)
SECOND_CAMERA = RIG[RIG.index("[[camera]]") : RIG.index("# optional")]


@pytest.mark.parametrize(
    ("kind", "text", "said"),
    [
        ("rig", RIG + "focal = 3\n", "camera[1].focal: unknown key"),
        ("rig", "colour = 1\n" + RIG, "colour: unknown key"),
        ("rig", RIG.replace('name = "cell-rig"\n', ""), "name: required key missing"),
        ("rig", 'name = "r"\n', "camera: at least one [[camera]] table is needed"),
        (
            "rig",
            RIG.replace(IDENTITY, NOT_RIGID),
            "camera[1].T_rig_cam: not a rigid transform "
            "(rotation not orthonormal with det +1 within 1e-06)",
        ),
        (
            "rig",
            RIG.replace("[0.0, 0.0, 0.0, 1.0]]", "[0.0, 0.0, 0.1, 1.0]]"),
            "camera[1].T_rig_cam: not a rigid transform (last row must be 0 0 0 1)",
        ),
        (
            "rig",
            RIG.replace("[0.0, 1000.0, 511.5]", "[5.0, 1000.0, 511.5]"),
            "camera[1].K: must be upper-triangular with last row 0 0 1",
        ),
        (
            "rig",
            RIG.replace("[[1000.0, 0.0,", "[[1000.0, 0.5,"),
            "camera[1].K: skew K[0][1] must be 0 (OpenCV's projection ignores it)",
        ),
        (
            "rig",
            RIG.replace("[[1000.0,", "[[-1000.0,"),
            "camera[1].K: focal lengths K[0][0] and K[1][1] must be positive",
        ),
        (
            "rig",
            RIG.replace("[0.0, 0.0, 1.0]]", "[0.0, 0.0, 2.0]]"),
            "camera[1].K: must be upper-triangular with last row 0 0 1",
        ),
        (
            "rig",
            RIG.replace("[0.0, 0.0, 0.0, 0.0, 0.0]", "[0.0, 0.0, 0.0, 0.0]"),
            "camera[1].dist: expected 5, 8, 12 or 14 coefficients (OpenCV's order)",
        ),
        ("rig", RIG.replace("1280", "0"), "camera[1].width: must be a positive integer, got 0"),
        (
            "rig",
            RIG.replace("1024", "10.5"),
            "camera[1].height: must be a positive integer, got 10.5",
        ),
        ("rig", RIG.replace("639.5", "nan"), "camera[1].K: not finite"),
        ("rig", RIG.replace("639.5", "true"), "camera[1].K: expected numbers, not true/false"),
        ("rig", RIG + SECOND_CAMERA, "camera[2].name: 'cam0' repeats camera[1]"),
        ("target", TARGET + "colour = 1\n", "marker[2].colour: unknown key"),
        (
            "target",
            TARGET.replace("DICT_4X4_50", "DICT_4X4_51"),
            "dictionary: 'DICT_4X4_51' is not a cv2.aruco predefined dictionary",
        ),
        (
            "target",
            TARGET.replace("DICT_4X4_50", "CORNER_REFINE_NONE"),
            "dictionary: 'CORNER_REFINE_NONE' is not a cv2.aruco predefined dictionary",
        ),
        (
            "target",
            TARGET.replace("id = 8", "id = 50"),
            "marker[2].id: 50 is not in DICT_4X4_50 (ids 0..49)",
        ),
        ("target", TARGET.replace("id = 8", "id = 7"), "marker[2].id: 7 repeats marker[1]"),
        (
            "target",
            TARGET.replace("size = 40.0  ", "size = -4.0  "),
            "marker[1].size: must be positive and finite, got -4",
        ),
        (
            "target",
            TARGET.replace("[0.0, 0.0, 0.0]  ", "[0.0, 0.0]  "),
            "reference: expected 3 numbers, got 2",
        ),
        ("board", BOARD.replace("22.0", "30.0"), "marker: 30 must be smaller than square (30)"),
        ("board", BOARD + "colour = 1\n", "colour: unknown key"),
        (
            "board",
            BOARD.replace("[7, 5]", "[7]"),
            "squares: expected [nx, ny], integers of at least 2",
        ),
        (
            "board",
            BOARD.replace("[7, 5]", "[20, 20]"),
            "squares: a 20×20 board needs 200 markers, DICT_5X5_100 has 100",
        ),
        ("board", BOARD.replace("false", "0"), "legacy: expected true or false, got 0"),
    ],
)
def test_refusals_are_one_line_naming_file_and_key(
    tmp_path: Path, kind: str, text: str, said: str
) -> None:
    path = _write(tmp_path, text)
    reader = {"rig": read_rig, "target": read_target, "board": read_board}[kind]
    with pytest.raises(FileFormatError) as info:
        reader(path)
    assert str(info.value) == f"{path}: {said}"
    assert "\n" not in str(info.value)


def test_dataclasses_refuse_without_a_file() -> None:
    with pytest.raises(InputError, match="camera: at least one"):
        Rig("r", ())
    with pytest.raises(InputError, match="marker: 40 must be smaller than square"):
        Board("DICT_4X4_50", (5, 7), 30.0, 40.0)


# --- the camera model -----------------------------------------------------------------------


def test_point_on_the_optical_axis_lands_on_the_principal_point() -> None:
    cam = _camera()
    p = (cam.T_rig_cam @ [0.0, 0.0, 1500.0, 1.0])[:3]
    np.testing.assert_allclose(cam.project(p[None]), [[cam.K[0, 2], cam.K[1, 2]]], atol=1e-9)


def test_projection_agrees_with_a_hand_pinhole_without_distortion() -> None:
    cam = _camera()
    rng = np.random.default_rng(0)
    p_cam = np.column_stack([rng.uniform(-300, 300, (20, 2)), rng.uniform(800, 2000, 20)])
    p_rig = p_cam @ cam.T_rig_cam[:3, :3].T + cam.T_rig_cam[:3, 3]
    u = cam.K[0, 0] * p_cam[:, 0] / p_cam[:, 2] + cam.K[0, 2]
    v = cam.K[1, 1] * p_cam[:, 1] / p_cam[:, 2] + cam.K[1, 2]
    np.testing.assert_allclose(cam.project(p_rig), np.column_stack([u, v]), atol=1e-8)


@pytest.mark.parametrize(
    "dist",
    [
        [-0.21, 0.08, 0.0012, -0.0007, -0.015],
        [-0.21, 0.08, 0.0012, -0.0007, -0.015, 0.01, -0.005, 0.002],
        [-0.1, 0.02, 0.001, 0.0, 0.0, 0.0, 0.0, 0.0, 0.001, -0.0005, 0.0007, 0.0002, 0.001, -0.002],
    ],
    ids=["5", "8", "14"],
)
def test_normalised_inverts_project_with_distortion(dist: list[float]) -> None:
    cam = _camera(dist=dist)
    rng = np.random.default_rng(1)
    p_cam = np.column_stack([rng.uniform(-400, 400, (30, 2)), rng.uniform(900, 1600, 30)])
    p_rig = p_cam @ cam.T_rig_cam[:3, :3].T + cam.T_rig_cam[:3, 3]
    px = cam.project(p_rig)
    assert np.abs(px - _camera().project(p_rig)).max() > 1.0  # the distortion matters
    np.testing.assert_allclose(cam.normalised(px), p_cam[:, :2] / p_cam[:, 2:], atol=1e-9)


def test_marker_corners_in_detector_order() -> None:
    m = Marker(3, 40.0, np.eye(4))
    np.testing.assert_array_equal(
        m.corners(), [[-20, 20, 0], [20, 20, 0], [20, -20, 0], [-20, -20, 0]]
    )
    T = _pose([0.4, 0.2, -1.1], [10.0, 20.0, 30.0])
    c = Marker(3, 40.0, T).corners()
    np.testing.assert_allclose(np.linalg.norm(np.diff(c, axis=0, append=c[:1]), axis=1), 40.0)
    np.testing.assert_allclose(c.mean(axis=0), T[:3, 3])
    # x right, y up, z out of the face: TL→TR along x, TR→BR along −y
    np.testing.assert_allclose((c[1] - c[0]) / 40.0, T[:3, 0], atol=1e-12)
    np.testing.assert_allclose((c[1] - c[2]) / 40.0, T[:3, 1], atol=1e-12)


@pytest.mark.parametrize("legacy", [False, True])
def test_board_gives_the_opencv_board(legacy: bool) -> None:
    board = Board("DICT_5X5_100", (7, 5), 30.0, 22.0, legacy)
    cv = board.cv_board()
    assert len(cv.getChessboardCorners()) == 6 * 4
    assert cv.getLegacyPattern() is legacy
    assert tuple(cv.getChessboardSize()) == (7, 5)
    assert cv.getSquareLength() == 30.0 and cv.getMarkerLength() == 22.0


def test_the_documented_examples_parse(tmp_path: Path) -> None:
    text = (Path(__file__).parents[1] / "docs" / "file-formats.md").read_text(encoding="utf-8")
    section = text[text.index("## Photogrammetry files") :]
    blocks = re.findall(r"^```toml\n(.*?)^```", section, re.S | re.M)
    assert len(blocks) == 3, "rig, target and board examples"
    for body, reader in zip(blocks, (read_rig, read_target, read_board), strict=True):
        reader(_write(tmp_path, body))
