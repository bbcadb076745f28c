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

from cellcal.calib.rig_measurement import TargetMeter
from cellcal.cli import main
from cellcal.drivers.camera_aravis import AravisCameraOptions, AravisRig, AravisRigOptions
from cellcal.photofiles import read_rig, read_target

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
