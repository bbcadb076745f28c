"""``cellcal rig measure --sets`` over a batch with bad files: every set is measured and
printed, a file that cannot be used is named and its camera left out, and the exit code
and one summary line say what was not measured."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cellcal.files.images import ImageFileError, read_image, write_image
from cellcal.files.photogrammetry import write_rig, write_target
from cellcal.mocks.rig.camera_render import Optics, SceneRenderer
from cellcal.mocks.rig.scene import dome_target, four_camera_rig, volume_centre
from tests.cli.test_rig_cli import measure_args, run
from tests.lazy import Rotation

#: set → pose (index into the poses rendered): two poses, each in several sets
SETS = {"set00": 0, "set01": 0, "set02": 1, "set03": 1, "set04": 0}


def truncate(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


@pytest.fixture(scope="module")
def batch(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Five sets of two poses, every camera seeing the target; ``clean`` as rendered,
    ``bad`` with: set01/cam1 truncated, set02/cam2 a text file, set03 readable only by
    cam0 (cam1 truncated, cam2 empty, cam3 a text file), set04/cam3 of the wrong size."""
    root = tmp_path_factory.mktemp("batch")
    rig, target = four_camera_rig(), dome_target()
    write_rig(root / "rig.toml", rig)
    write_target(root / "target.toml", target)
    renderer = SceneRenderer.for_target(rig.cameras, target, Optics())
    rng = np.random.default_rng(11)
    poses = []
    for dx, tilt in [(10.0, 5.0), (-50.0, -10.0)]:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xy", [180.0, tilt], degrees=True).as_matrix()
        T[:3, 3] = volume_centre(rig) + np.array([dx, -15.0, 20.0])
        poses.append(T)
    clean = root / "clean"
    for name, k in SETS.items():
        (clean / name).mkdir(parents=True)
        for cam, img in renderer.frames(renderer.clean(poses[k]), rng).items():
            write_image(clean / name / f"{cam}.png", img)
    bad = root / "bad"
    shutil.copytree(clean, bad)
    truncate(bad / "set01" / "cam1.png")
    (bad / "set02" / "cam2.png").write_text("not a picture\n")
    truncate(bad / "set03" / "cam1.png")
    (bad / "set03" / "cam2.png").write_bytes(b"")
    (bad / "set03" / "cam3.png").write_text("hello")
    write_image(bad / "set04" / "cam3.png", np.zeros((10, 10), np.uint8))
    return {"root": root, "clean": clean, "bad": bad, "truths": [T[:3, 3] for T in poses]}


def test_a_clean_batch_exits_0(capsys: pytest.CaptureFixture[str], batch: dict) -> None:
    root: Path = batch["root"]
    code, out, err = run(capsys, *measure_args(root), "--sets", batch["clean"], "--json")
    assert code == 0 and err == ""
    lines = [json.loads(x) for x in out.splitlines()]
    assert [x["set"] for x in lines] == list(SETS)
    for line in lines:
        assert line["cameras"] == ["cam0", "cam1", "cam2", "cam3"]
        assert line["unreadable"] == []
        truth = batch["truths"][SETS[line["set"]]]
        assert np.linalg.norm(np.array(line["xyz_mm"]) - truth) < 0.1
    code, out, err = run(capsys, *measure_args(root), "--sets", batch["clean"])
    assert code == 0 and err == "" and out.count(" mm  (1σ ") == 5 and "left out" not in out


def test_bad_files_are_named_and_the_batch_goes_on(
    capsys: pytest.CaptureFixture[str], batch: dict
) -> None:
    root: Path = batch["root"]
    bad: Path = batch["bad"]
    code, out, err = run(capsys, *measure_args(root), "--sets", bad, "--json")
    assert code == 2
    lines = {x["set"]: x for x in map(json.loads, out.splitlines())}  # stdout: JSON only
    assert list(lines) == list(SETS)  # every set, in order

    def xyz(name: str) -> np.ndarray:
        return np.array(lines[name]["xyz_mm"])

    def agree(a: str, b: str) -> bool:
        """Two sets of one pose: within 4σ of their reported uncertainties (each set's
        frames have their own noise)."""
        d = xyz(a) - xyz(b)
        cov = np.array(lines[a]["cov_mm2"]) + np.array(lines[b]["cov_mm2"])
        return float(d @ np.linalg.solve(cov, d)) < 4.0**2 and np.linalg.norm(d) < 0.15

    # set01: measured by the three other cameras, where set00 (same pose) puts it
    assert lines["set01"]["unreadable"] == [
        {
            "camera": "cam1",
            "path": str(bad / "set01" / "cam1.png"),
            "error": "not a complete image: truncated PNG",
        }
    ]
    assert lines["set01"]["cameras"] == ["cam0", "cam2", "cam3"]
    assert agree("set01", "set00")
    assert np.linalg.norm(xyz("set01") - batch["truths"][0]) < 0.1
    # set02: a text file named .png
    assert [(u["camera"], u["error"]) for u in lines["set02"]["unreadable"]] == [
        ("cam2", "not an image: a text file")
    ]
    assert lines["set02"]["cameras"] == ["cam0", "cam1", "cam3"]
    assert np.linalg.norm(xyz("set02") - batch["truths"][1]) < 0.1
    # set03: one readable image is not enough; the set is skipped with its reasons
    assert set(lines["set03"]) == {"set", "error", "unreadable"}
    assert "seen by 1 camera(s) (cam0)" in lines["set03"]["error"]
    assert [(u["camera"], u["error"]) for u in lines["set03"]["unreadable"]] == [
        ("cam1", "not a complete image: truncated PNG"),
        ("cam2", "empty file, not an image"),
        ("cam3", "not an image: a text file"),
    ]
    # set04: an image of another size than the rig's camera is left out, not fatal
    assert [(u["camera"], u["error"]) for u in lines["set04"]["unreadable"]] == [
        ("cam3", "10×10 px, but camera cam3 is 1280×1024 in the rig file")
    ]
    assert agree("set04", "set00")
    assert lines["set00"]["unreadable"] == []
    # stderr: one line per file (its path and why), then the summary
    errs = err.splitlines()
    assert len(errs) == 7
    assert errs[0] == (
        f"cellcal: rig measure: {bad / 'set01' / 'cam1.png'}: not a complete image: "
        "truncated PNG; cam1 left out of set01"
    )
    assert f"{bad / 'set02' / 'cam2.png'}: not an image: a text file" in errs[1]
    assert f"{bad / 'set03' / 'cam2.png'}: empty file" in errs[3]
    assert f"{bad / 'set04' / 'cam3.png'}: 10×10 px" in errs[5]
    assert errs[6] == (
        "cellcal: error: rig measure: 4 of 5 sets measured; 6 images unreadable "
        "(set01/cam1.png: not a complete image: truncated PNG; "
        "set02/cam2.png: not an image: a text file; "
        "set03/cam1.png: not a complete image: truncated PNG; and 3 more); "
        "1 set skipped (set03)"
    )


def test_bad_files_in_the_text_output(capsys: pytest.CaptureFixture[str], batch: dict) -> None:
    root: Path = batch["root"]
    code, out, err = run(capsys, *measure_args(root), "--sets", batch["bad"])
    assert code == 2
    lines = out.splitlines()
    assert [x.split(":")[0] for x in lines] == list(SETS)
    assert out.count(" mm  (1σ ") == 4
    assert lines[1].endswith("(cam1 left out: not a complete image: truncated PNG)")
    assert "3 cameras cam0,cam2,cam3" in lines[1]
    assert "seen by 1 camera(s) (cam0)" in lines[3]
    assert lines[3].endswith(
        "(cam1 left out: not a complete image: truncated PNG; "
        "cam2 left out: empty file, not an image; cam3 left out: not an image: a text file)"
    )
    assert "left out" not in lines[0]
    assert err.splitlines()[-1].startswith("cellcal: error: rig measure: 4 of 5 sets measured;")


def test_no_set_measured(capsys: pytest.CaptureFixture[str], batch: dict, tmp_path: Path) -> None:
    root: Path = batch["root"]
    for name in ("a", "b"):
        shutil.copytree(batch["bad"] / "set03", tmp_path / name)
    (tmp_path / "c").mkdir()  # no image at all
    code, out, err = run(capsys, *measure_args(root), "--sets", tmp_path, "--json")
    assert code == 2
    lines = [json.loads(x) for x in out.splitlines()]
    assert [set(x) for x in lines] == [{"set", "error", "unreadable"}] * 3
    assert lines[2]["error"].startswith("no image of the rig's cameras (cam0, cam1")
    assert err.splitlines()[-1].startswith(
        "cellcal: error: rig measure: 0 of 3 sets measured; 6 images unreadable"
    )
    assert err.splitlines()[-1].endswith("; 3 sets skipped (a, b, c)")


def test_fatal_up_front(capsys: pytest.CaptureFixture[str], batch: dict, tmp_path: Path) -> None:
    """A file of a camera not in the rig, no directory, no sets: one line, nothing measured."""
    root: Path = batch["root"]
    sets = tmp_path / "sets"
    shutil.copytree(batch["clean"], sets)
    shutil.copy(sets / "set02" / "cam0.png", sets / "set02" / "cam7.png")
    shutil.copy(sets / "set03" / "cam0.png", sets / "set03" / "cam8.png")
    code, out, err = run(capsys, *measure_args(root), "--sets", sets, "--json")
    assert code == 2 and out == "" and err.count("\n") == 1
    assert f"{sets / 'set02' / 'cam7.png'}: 'cam7' is not a camera of rig" in err
    assert "1 more such files" in err
    code, out, err = run(capsys, *measure_args(root), "--sets", tmp_path / "nowhere")
    assert code == 2 and out == "" and "not a directory of image sets" in err
    (tmp_path / "empty").mkdir()
    code, out, err = run(capsys, *measure_args(root), "--sets", tmp_path / "empty")
    assert code == 2 and out == "" and "no image sets" in err


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a complete image: truncated PNG"),
        (b"\x89PNG\r\n\x1a\n garbage \x00\x00\x00\x00IEND\xaeB`\x82", "damaged PNG"),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "not a complete image: truncated or damaged JPEG"),
        ("x,y,z\n1,2,3\nµm\n".encode(), "not an image: a text file"),
        (bytes(range(256)), "not an image: no image format OpenCV reads"),
        (b"", "empty file, not an image"),
    ],
    ids=["truncated-png", "damaged-png", "jpeg", "text", "binary", "empty"],
)
def test_why_an_image_cannot_be_read(tmp_path: Path, content: bytes, reason: str) -> None:
    p = tmp_path / "cam0.png"
    p.write_bytes(content)
    with pytest.raises(ImageFileError) as err:
        read_image(p)
    assert err.value.path == p and reason in err.value.reason
    assert str(err.value) == f"{p}: {err.value.reason}"
