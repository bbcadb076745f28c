"""``cellcal rig measure`` through the entry point, on images the camera twin rendered."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli import main
from cellcal.files.images import write_image
from cellcal.files.photogrammetry import write_rig, write_target
from cellcal.mocks.rig.camera_render import Optics, SceneRenderer
from cellcal.mocks.rig.scene import board_poses, dome_target, four_camera_rig, volume_centre
from tests.calib.detections import kept_detections
from tests.lazy import Rotation

pytestmark = pytest.mark.slow  # renders and calibrates a rig: the parallel run starts it early


def measure_args(root: Path) -> list[object]:
    return ["rig", "measure", "--rig", root / "rig.toml", "--target", root / "target.toml"]


def run(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return int(exc.value.code or 0), out, err


@pytest.fixture(scope="module", autouse=True)
def _detections() -> Iterator[object]:
    """Views calibrated twice are detected once (tests/calib/detections.py)."""
    yield from kept_detections()


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("rig")
    rig, target = four_camera_rig(), dome_target()
    write_rig(root / "rig.toml", rig)
    write_target(root / "target.toml", target)
    renderer = SceneRenderer.for_target(rig.cameras, target, Optics())
    rng = np.random.default_rng(5)
    truths = []
    for k, (dx, tilt) in enumerate([(0.0, 0.0), (60.0, 12.0), (-80.0, -15.0)]):
        T = np.eye(4)
        R = Rotation.from_euler("xy", [180.0, tilt], degrees=True)
        T[:3, :3] = R.as_matrix()
        T[:3, 3] = volume_centre(rig) + np.array([dx, 20.0, -30.0])
        folder = root / "sets" / f"set{k:02d}"
        folder.mkdir(parents=True)
        for cam, img in renderer.frames(renderer.clean(T), rng).items():
            write_image(folder / f"{cam}.png", img)
        truths.append(T[:3, 3])
    # a set only one camera sees: the others' images are blank
    lonely = root / "sets" / "set03"
    lonely.mkdir()
    for cam in ("cam0", "cam1", "cam2", "cam3"):
        src = root / "sets" / "set00" / f"{cam}.png"
        img = np.full((1024, 1280), 40, np.uint8) if cam != "cam0" else None
        if img is None:
            lonely.joinpath(f"{cam}.png").write_bytes(src.read_bytes())
        else:
            write_image(lonely / f"{cam}.png", img)
    return {"root": root, "truths": truths}


def test_one_set_json(capsys: pytest.CaptureFixture[str], scene: dict) -> None:
    root: Path = scene["root"]
    images = [f"--image=cam{k}={root / 'sets' / 'set01' / f'cam{k}.png'}" for k in range(4)]
    code, out, err = run(capsys, *measure_args(root), *images, "--json")
    assert code == 0, err
    got = json.loads(out)
    assert set(got) >= {
        "xyz_mm",
        "cov_mm2",
        "T_rig_target",
        "cameras",
        "markers",
        "reprojection_rms_px",
    }
    assert np.linalg.norm(np.array(got["xyz_mm"]) - scene["truths"][1]) < 0.1
    assert np.array(got["cov_mm2"]).shape == (3, 3)
    assert len(got["cameras"]) >= 2 and got["markers"] >= 2


def test_sets_go_on_past_a_set_the_rig_cannot_measure(
    capsys: pytest.CaptureFixture[str], scene: dict
) -> None:
    root: Path = scene["root"]
    code, out, err = run(capsys, *measure_args(root), "--sets", root / "sets", "--json")
    # every set printed; one not measured: exit 2 after the last, with one summary line
    assert code == 2
    assert err == "cellcal: error: rig measure: 3 of 4 sets measured; 1 set skipped (set03)\n"
    lines = [json.loads(x) for x in out.splitlines()]
    assert [x["set"] for x in lines] == ["set00", "set01", "set02", "set03"]
    for line, truth in zip(lines[:3], scene["truths"], strict=True):
        assert np.linalg.norm(np.array(line["xyz_mm"]) - truth) < 0.1
    assert "seen by 1 camera(s) (cam0)" in lines[3]["error"]
    code, out, _ = run(capsys, *measure_args(root), "--sets", root / "sets")
    assert code == 2 and out.count(" mm  (1σ ") == 3


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda p: p.write_bytes(p.read_bytes()[:2000]), "not a complete image: truncated PNG"),
        (lambda p: p.write_bytes(b""), "empty file"),
        (lambda p: p.write_text("hello"), "not an image: a text file"),
        (lambda p: p.unlink(), "no such image"),
    ],
    ids=["truncated", "empty", "text", "missing"],
)
def test_bad_images_end_in_one_line(
    capsys: pytest.CaptureFixture[str], scene: dict, tmp_path: Path, mutate: object, message: str
) -> None:
    root: Path = scene["root"]
    bad = tmp_path / "cam1.png"
    bad.write_bytes((root / "sets" / "set00" / "cam1.png").read_bytes())
    mutate(bad)  # type: ignore[operator]
    code, out, err = run(
        capsys,
        *measure_args(root),
        f"--image=cam0={root / 'sets' / 'set00' / 'cam0.png'}",
        f"--image=cam1={bad}",
    )
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and message in err and "cam1.png" in err


def test_usage_errors(capsys: pytest.CaptureFixture[str], scene: dict) -> None:
    root: Path = scene["root"]
    base = measure_args(root)
    code, _, err = run(capsys, *base)
    assert code == 2 and "either --image" in err
    code, _, err = run(capsys, *base, "--image", "cam7=x.png")
    assert code == 2 and "not a camera of rig" in err
    code, _, err = run(capsys, *base, "--image", "cam0")
    assert code == 2 and "expected CAM=PATH" in err
    small = root / "small.png"
    write_image(small, np.zeros((10, 10), np.uint8))
    code, _, err = run(capsys, *base, "--image", f"cam0={small}")
    assert code == 2 and "10×10 px, but camera cam0 is 1280×1024" in err


def test_rig_calibrate_writes_a_rig_that_measures(
    capsys: pytest.CaptureFixture[str], scene: dict, tmp_path: Path
) -> None:
    """ChArUco views rendered for the simulated rig → `rig calibrate` → a rig file within
    its reported uncertainty of the truth, with which `rig measure` gets lengths right."""
    from cellcal.files.photogrammetry import read_rig, write_board
    from tests.calib.test_rig_calibration import BOARD

    rig = four_camera_rig()
    renderer = SceneRenderer.for_board(rig.cameras, BOARD, Optics(supersample=3))
    rng = np.random.default_rng(9)
    for k, T in enumerate(board_poses(rig, BOARD, 12, seed=3)):
        for cam, img in renderer.frames(renderer.clean(T), rng).items():
            (tmp_path / "views" / f"v{k}").mkdir(parents=True, exist_ok=True)
            write_image(tmp_path / "views" / f"v{k}" / f"{cam}.png", img)
    write_board(tmp_path / "board.toml", BOARD)
    out = tmp_path / "rig.toml"
    code, text, err = run(
        capsys,
        "rig",
        "calibrate",
        "--board",
        tmp_path / "board.toml",
        "--views",
        tmp_path / "views",
        "--out",
        out,
        "--fix-k3",
        "--fix-tangential",
        "--json",
    )
    assert code == 0, err
    got = json.loads(text)
    assert got["verdict"] == "passes" and got["failures"] == []
    assert "accepted_despite" not in out.read_text()
    assert [c["name"] for c in got["cameras"]] == ["cam0", "cam1", "cam2", "cam3"]
    assert got["holdout"]["reprojection_rms_px"] < 0.2
    calibrated = read_rig(out)
    for truth, cam, rep in zip(rig.cameras, calibrated.cameras, got["cameras"], strict=True):
        # 9 fitted views: millimetres, as the reported 1σ says
        error = np.linalg.norm(cam.T_rig_cam[:3, 3] - truth.T_rig_cam[:3, 3])
        assert error <= 4.0 * np.linalg.norm(rep["sigma_position_mm"]) + 1e-9
        assert abs(cam.K[0, 0] - truth.K[0, 0]) <= 4.0 * rep["sigma_fx_px"] + 1e-9
    # a length between two measured target positions (VDI/VDE 2634-1 style): the rig's
    # frame is its own, lengths are what a calibration must get right
    root: Path = scene["root"]
    base = ["rig", "measure", "--rig", out, "--target", root / "target.toml"]
    code, text, err = run(capsys, *base, "--sets", root / "sets", "--json")
    assert code == 2 and "3 of 4 sets measured; 1 set skipped (set03)" in err, err
    xyz = [np.array(json.loads(line)["xyz_mm"]) for line in text.splitlines()[:3]]
    for a, b in ((0, 1), (1, 2), (0, 2)):
        length = np.linalg.norm(scene["truths"][a] - scene["truths"][b])
        assert abs(np.linalg.norm(xyz[a] - xyz[b]) - length) < 0.3


def test_rig_calibrate_refuses_a_failed_check_unless_accepted(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A held-out check that fails (here: a length limit no rig meets) is refused with
    exit 3, its numbers on the line and no rig file; --accept writes it with the failure
    recorded, and the file still reads."""
    from cellcal.files.photogrammetry import read_rig, write_board
    from tests.calib.test_rig_calibration import BOARD

    rig = four_camera_rig()
    renderer = SceneRenderer.for_board(rig.cameras, BOARD, Optics(supersample=3))
    rng = np.random.default_rng(4)
    for k, T in enumerate(board_poses(rig, BOARD, 10, seed=8)):
        for cam, img in renderer.frames(renderer.clean(T), rng).items():
            (tmp_path / "views" / f"v{k}").mkdir(parents=True, exist_ok=True)
            write_image(tmp_path / "views" / f"v{k}" / f"{cam}.png", img)
    write_board(tmp_path / "board.toml", BOARD)
    out = tmp_path / "rig.toml"
    args = ["rig", "calibrate", "--board", tmp_path / "board.toml", "--views"]
    args += [tmp_path / "views", "--out", out, "--fix-k3", "--fix-tangential"]
    code, text, err = run(capsys, *args, "--max-length-error", "0.00001")
    assert code == 3 and not out.exists() and text == ""
    # what it is doing, as it begins each slow part; then the refusal, in one line
    *progress, err = err.strip().splitlines()
    assert progress == [
        f"rig calibrate: reading the views in {tmp_path / 'views'}…",
        "rig calibrate: 10 views of 4 cameras: finding the board, measuring its corners from "
        "their edges, adjusting the bundle…",
    ]
    assert err.startswith("cellcal: refused: rig calibration: held-out board lengths are off by")
    assert "beyond 1e-05 mm" in err
    code, text, err = run(capsys, *args, "--max-length-error", "0.00001", "--accept")
    assert code == 0, err
    assert "verdict: fails, written with --accept (held-out board lengths" in text
    assert "accepted_despite = [" in out.read_text()
    assert [c.name for c in read_rig(out).cameras] == ["cam0", "cam1", "cam2", "cam3"]
    code, _, err = run(capsys, *args, "--max-length-error", "-1")
    assert code == 2 and "--max-length-error: expected a positive length" in err
