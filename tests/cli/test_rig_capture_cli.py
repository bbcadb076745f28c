"""``cellcal mock cameras`` served to the aravis driver and measured; ``cellcal rig
capture`` from a configured rig (a recording played back through the files backend)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cellcal.calib.photogrammetry.rig_measurement import TargetMeter
from cellcal.cli import main
from cellcal.drivers.cameras.aravis import AravisCameraOptions, AravisRig, AravisRigOptions
from cellcal.files.photogrammetry import read_rig, read_target

pytestmark = [pytest.mark.twin, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
RIG, TARGET = ROOT / "config" / "mock-rig.toml", ROOT / "config" / "mock-target.toml"


def _run(capsys, *args: object) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return int(exc.value.code or 0), out, err


@pytest.mark.timeout(90)
def test_mock_cameras_serve_the_simulated_cell_to_the_aravis_driver():
    proc = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "cameras", "--rig", RIG, "--target", TARGET],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines = [proc.stdout.readline() for _ in range(5)]  # waits for the cameras to listen
        assert lines[0].startswith("camera cam0: GigE Vision at 127.0.0.2"), lines
        netns = re.search(r"network namespace: (\S+)", lines[4]).group(1)
        cameras = [
            AravisCameraOptions(name=f"cam{k}", address=f"127.0.0.{k + 2}", timeout_s=5.0)
            for k in range(4)
        ]
        rig = AravisRig.from_options(AravisRigOptions(cameras=cameras, netns=netns))
        rig.connect()
        try:
            frames = rig.grab()
        finally:
            rig.close()
        assert not frames.lost
        pose = TargetMeter(read_rig(RIG), read_target(TARGET)).measure(
            {c: f.image for c, f in frames.frames.items()}
        )
        assert len(pose.cameras) >= 2 and np.isfinite(pose.xyz_mm).all()
        assert pose.reprojection_rms_px < 0.5
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, proc.stderr.read()


def test_mock_cameras_hosts_are_checked(capsys):
    code, _, err = _run(
        capsys, "mock", "cameras", "--rig", RIG, "--target", TARGET, "--hosts", "10.0.0.2-5"
    )
    assert code == 2 and err.strip().splitlines()[-1].startswith("cellcal: error: --hosts")


def test_rig_capture_writes_sets_the_files_backend_reads_again(tmp_path, capsys):
    recording = tmp_path / "recording"
    for k in range(2):
        (recording / f"set-{k}").mkdir(parents=True)
        for cam in ("cam0", "cam1"):
            image = np.full((48, 64), 40 + 10 * k, dtype=np.uint8)
            image[10:20, 10:20] = 200
            cv2.imwrite(str(recording / f"set-{k}" / f"{cam}.png"), image)
    config = tmp_path / "cell.toml"
    config.write_text(
        "[[sensor]]\nname = 'tracker'\nkind = 'laser-tracker'\nreference = true\n"
        "[[sensor]]\nname = 'rig'\nkind = 'photogrammetry'\nrig_file = 'rig.toml'\n"
        "target_file = 'target.toml'\n"
        "[sensor.capture]\nbackend = 'files'\ndirectory = 'recording'\n"
        "cameras = [{ name = 'cam0' }, { name = 'cam1' }]\n"
    )
    code, out, err = _run(
        capsys, "rig", "capture", "--config", config, "--out", tmp_path / "out", "--sets", 2,
        "--json",
    )  # fmt: skip
    assert code == 0, err
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["set"] for r in records] == ["set-0001", "set-0002"]
    assert all(r["lost"] == {} for r in records)
    got = cv2.imread(str(tmp_path / "out" / "set-0002" / "cam1.png"), cv2.IMREAD_GRAYSCALE)
    assert got[0, 0] == 50 and got[15, 15] == 200
    # a configuration without a rig is one line
    bare = tmp_path / "bare.toml"
    bare.write_text("[[sensor]]\nname = 't'\nkind = 'laser-tracker'\nreference = true\n")
    code, _, err = _run(capsys, "rig", "capture", "--config", bare, "--out", tmp_path / "o2")
    assert code == 2 and "no photogrammetry sensor" in err.strip().splitlines()[-1]


BOARD = ROOT / "config" / "mock-board.toml"


def _board_in_rig(images: dict, rig, board) -> np.ndarray:
    """Each camera's pose of the board, in the rig frame (solvePnP on its corners)."""
    from cellcal.calib.photogrammetry.board_corners import board_points, detect_corners

    points, out = board_points(board), []
    for name, image in images.items():
        d = detect_corners(board, image)
        assert d is not None, name
        cam = rig.camera(name)
        _, rvec, tvec = cv2.solvePnP(points[d.ids], d.pixels, cam.K, cam.dist)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        out.append((cam.T_rig_cam @ T)[:3, 3])
    return np.array(out)


@pytest.mark.timeout(120)
def test_mock_cameras_serve_board_views_a_set_at_a_time():
    """With --board every camera of a set sees the board at one pose (within a
    millimetre), and the next set at another."""
    from cellcal.files.photogrammetry import read_board

    proc = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "cameras", "--rig", RIG, "--board", BOARD,
         "--views", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        lines = [proc.stdout.readline() for _ in range(5)]  # waits for the cameras to listen
        assert lines[0].startswith("camera cam0: GigE Vision at 127.0.0.2"), lines
        netns = re.search(r"network namespace: (\S+)", lines[4]).group(1)
        cameras = [
            AravisCameraOptions(name=f"cam{k}", address=f"127.0.0.{k + 2}", timeout_s=5.0)
            for k in range(4)
        ]
        rig = AravisRig.from_options(AravisRigOptions(cameras=cameras, netns=netns))
        rig.connect()
        try:
            sets = [rig.grab() for _ in range(3)]
        finally:
            rig.close()
        truth, board = read_rig(RIG), read_board(BOARD)
        where = [
            _board_in_rig({c: f.image for c, f in s.frames.items()}, truth, board) for s in sets
        ]
        for w in where:
            assert np.ptp(w, axis=0).max() < 1.0, w
        assert np.linalg.norm(where[0][0] - where[1][0]) > 10.0
        assert np.linalg.norm(where[1][0] - where[2][0]) > 10.0
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, proc.stderr.read()


def test_mock_cameras_take_a_target_or_a_board(capsys):
    for extra in ([], ["--target", TARGET, "--board", BOARD]):
        code, _, err = _run(capsys, "mock", "cameras", "--rig", RIG, *extra)
        assert code == 2 and "give either --target FILE" in err.strip().splitlines()[-1]


@pytest.mark.timeout(180)
def test_from_nothing_to_a_calibrated_rig_and_a_measured_target(tmp_path, capsys):
    """The walk-through of docs/photogrammetry.md: board views from the simulated cell's
    cameras, `rig calibrate` on them (it passes, the cameras within their reported
    uncertainty of the twin's true rig), then the target measured with that rig: every
    set, within 0.05 mm of each other."""
    code, out, err = _run(
        capsys, "rig", "capture", "--mock", "--board", BOARD, "--sets", 12, "--out",
        tmp_path / "views", "--json",
    )  # fmt: skip
    assert code == 0, err
    assert [json.loads(line)["lost"] for line in out.splitlines()] == [{}] * 12
    rig_file = tmp_path / "my-rig.toml"
    code, out, err = _run(
        capsys, "rig", "calibrate", "--board", BOARD, "--views", tmp_path / "views",
        "--out", rig_file, "--json",
    )  # fmt: skip
    assert code == 0, err
    got = json.loads(out)
    assert got["verdict"] == "passes" and got["suspect_cameras"] == []
    assert got["holdout"]["length_rms_mm"] < 0.03
    truth, calibrated = read_rig(RIG), read_rig(rig_file)
    for t, c, rep in zip(truth.cameras, calibrated.cameras, got["cameras"], strict=True):
        error = np.linalg.norm(c.T_rig_cam[:3, 3] - t.T_rig_cam[:3, 3])
        assert error <= 4.0 * np.linalg.norm(rep["sigma_position_mm"]) + 1e-9, c.name
        assert abs(c.K[0, 0] - t.K[0, 0]) <= 4.0 * rep["sigma_fx_px"] + 0.05, c.name
    code, _, err = _run(capsys, "rig", "capture", "--mock", "--sets", 3, "--out", tmp_path / "s")
    assert code == 0, err
    code, out, err = _run(
        capsys, "rig", "measure", "--rig", rig_file, "--target", TARGET, "--sets",
        tmp_path / "s", "--json",
    )  # fmt: skip
    assert code == 0, err
    xyz = np.array([json.loads(line)["xyz_mm"] for line in out.splitlines()])
    assert len(xyz) == 3 and np.ptp(xyz, axis=0).max() < 0.05


def test_board_and_seed_need_mock(capsys, tmp_path):
    code, _, err = _run(
        capsys, "rig", "capture", "--config", ROOT / "config" / "mock-cell.toml", "--board",
        BOARD, "--out", tmp_path / "o",
    )  # fmt: skip
    assert code == 2 and "--board and --seed are for --mock" in err
