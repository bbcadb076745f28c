"""The ``files`` rig: recorded sets played back in order, 8/16-bit grey and colour, each
unusable image named in ``lost`` with its reason, and one clear end."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pydantic
import pytest

from cellcal.drivers.cameras.backends import rig_class
from cellcal.drivers.cameras.files import FilesRig, FilesRigOptions
from cellcal.errors import DeviceError

CAMERAS = ["left", "right"]


def pattern(k: int, dtype: type = np.uint8, shape: tuple[int, int] = (48, 64)) -> np.ndarray:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return ((xx + 2 * yy + 7 * k) % 200).astype(dtype)


def rig(directory: Path, **kw: object) -> FilesRig:
    cameras = [{"name": n} for n in CAMERAS]
    opts = FilesRigOptions.model_validate({"directory": str(directory), "cameras": cameras, **kw})
    r = FilesRig(opts)
    r.connect()
    return r


def write_sets(root: Path, n: int) -> None:
    for k in range(n):
        folder = root / f"set{k:03d}"
        folder.mkdir(parents=True)
        for i, name in enumerate(CAMERAS):
            cv2.imwrite(str(folder / f"{name}.png"), pattern(10 * k + i))


def test_sets_in_order_then_a_clear_end(tmp_path: Path) -> None:
    write_sets(tmp_path, 3)
    r = rig(tmp_path)
    assert r.remaining == 3 and rig_class("files") is FilesRig
    for k in range(3):
        s = r.grab()
        assert s.lost == {} and list(s.frames) == CAMERAS
        for i, name in enumerate(CAMERAS):
            f = s.frames[name]
            assert f.frame_id == k + 1 and f.retries == 0
            assert np.array_equal(f.image, pattern(10 * k + i))
    with pytest.raises(DeviceError, match=f"^no more image sets in {tmp_path}$"):
        r.grab()
    r.close()
    r.close()


def test_sixteen_bit_and_colour(tmp_path: Path) -> None:
    folder = tmp_path / "a"
    folder.mkdir()
    deep = pattern(3, np.uint16) * 300
    cv2.imwrite(str(folder / "left.png"), deep)
    colour = np.dstack([pattern(1), pattern(2), pattern(4)])
    cv2.imwrite(str(folder / "right.png"), colour)
    s = rig(tmp_path).grab()
    assert s.frames["left"].image.dtype == np.uint16
    assert np.array_equal(s.frames["left"].image, deep)
    right = s.frames["right"].image
    assert right.dtype == np.uint8 and right.shape == (48, 64)
    assert np.array_equal(right, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        ("truncate", "right.png: not a complete image"),
        ("garbage", "right.png: not a complete image"),
        ("blank", "is blank (every pixel 17)"),
        ("missing", "right.png: no such image"),
        ("float", "float32 pixels; 8- or 16-bit images expected"),
    ],
)
def test_unusable_image_is_lost_with_its_reason(tmp_path: Path, damage: str, reason: str) -> None:
    write_sets(tmp_path, 2)
    target = tmp_path / "set000" / "right.png"
    if damage == "truncate":
        data = target.read_bytes()
        target.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        target.write_bytes(b"\x89PNG not really")
    elif damage == "blank":
        cv2.imwrite(str(target), np.full((48, 64), 17, np.uint8))
    elif damage == "missing":
        target.unlink()
    else:
        target.unlink()
        target = target.with_suffix(".tiff")
        cv2.imwrite(str(target), pattern(1).astype(np.float32))
        cv2.imwrite(str(tmp_path / "set001" / target.name), pattern(2))
    r = rig(tmp_path, cameras=[{"name": "left"}, {"name": "right", "address": target.name}])
    s = r.grab()
    assert list(s.frames) == ["left"] and list(s.lost) == ["right"]
    assert reason in s.lost["right"] and "\n" not in s.lost["right"]
    assert set(r.grab().frames) == {"left", "right"}  # the next set is whole again


def test_no_sets_and_bad_options(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="no image sets in"):
        rig(tmp_path)
    with pytest.raises(DeviceError, match="cannot list"):
        rig(tmp_path / "absent")
    with pytest.raises(pydantic.ValidationError):
        FilesRigOptions.model_validate({"directory": "x", "cameras": []})
    with pytest.raises(pydantic.ValidationError):
        FilesRigOptions.model_validate({"directory": "x", "cameras": [{"name": "a b"}]})
    with pytest.raises(pydantic.ValidationError, match="camera names must be distinct"):
        FilesRigOptions.model_validate({"directory": "x", "cameras": [{"name": "a"}] * 2})
