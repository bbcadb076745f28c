"""Camera images on disk: one image, or sets of images (one folder per set, one image per
camera named ``<camera>.png``), read at the edge with one clear line per fault.

Images are 8- or 16-bit, grey or colour, in any format OpenCV decodes (PNG is what
cellcal writes). A missing, unreadable, truncated or empty file, or one that is not an
image, is a :class:`~cellcal.errors.FileFormatError` that names it; OpenCV's own
warnings about broken files are kept off the terminal.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.marker_corners import grey
from cellcal.errors import FileFormatError, InputError

#: Larger image files are refused (a 16-bit 20-megapixel PNG is about 40 MB).
MAX_IMAGE_BYTES = 200 * 1024 * 1024

Image = NDArray[Any]


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def read_image(path: str | Path) -> Image:
    """One image as OpenCV decodes it (grey (h, w) or colour (h, w, 3|4); uint8/uint16)."""
    p = Path(path)
    if not p.exists():
        raise FileFormatError(f"{p}: no such image")
    if not p.is_file():
        raise FileFormatError(f"{p}: not a regular file, not an image")
    size = p.stat().st_size
    if size == 0:
        raise FileFormatError(f"{p}: empty file, not an image")
    if size > MAX_IMAGE_BYTES:
        raise FileFormatError(f"{p}: {size / 1e6:.0f} MB is too large for an image")
    try:
        data = np.fromfile(p, dtype=np.uint8)
    except OSError as exc:
        raise FileFormatError(f"{p}: cannot be read ({exc.strerror})") from None
    with _quiet_opencv():
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileFormatError(f"{p}: not a complete image (truncated, or not an image format)")
    if img.dtype not in (np.uint8, np.uint16):
        raise FileFormatError(f"{p}: {img.dtype} pixels; 8- or 16-bit images expected")
    out: Image = img
    return out


def image_option(specs: tuple[str, ...]) -> dict[str, Path]:
    """``--image CAM=PATH`` options as {camera: path}; each camera once."""
    out: dict[str, Path] = {}
    for spec in specs:
        cam, sep, path = spec.partition("=")
        if not sep or not cam or not path:
            raise InputError(f"--image {spec!r}: expected CAM=PATH, e.g. cam0=cam0.png")
        if cam in out:
            raise InputError(f"--image: camera {cam!r} given twice")
        out[cam] = Path(path)
    return out


def natural_key(name: str) -> list[object]:
    """Sort key that orders embedded numbers by value (``cam2`` before ``cam10``)."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def set_folders(root: str | Path) -> list[Path]:
    """The set folders of an image-set directory (hidden ones skipped), in natural order."""
    p = Path(root)
    if not p.is_dir():
        raise FileFormatError(f"{p}: not a directory of image sets")
    folders = sorted(
        (d for d in p.iterdir() if d.is_dir() and not d.name.startswith(".")),
        key=lambda d: natural_key(d.name),
    )
    if not folders:
        raise FileFormatError(f"{p}: no image sets (one folder per set, <camera>.png in each)")
    return folders


@dataclass(frozen=True, eq=False)
class ViewSet:
    """Image sets read from a directory: their folder names, the cameras found (name →
    (width, height), in natural order) and per set the grey images by camera name."""

    names: tuple[str, ...]
    cameras: dict[str, tuple[int, int]]
    views: tuple[dict[str, Image], ...]


def load_views(directory: str | Path) -> ViewSet:
    """Every set under ``directory`` with its ``<camera>.png`` images, as grey. A
    camera's images must all have one size."""
    sizes: dict[str, tuple[int, int]] = {}
    first: dict[str, Path] = {}
    views = []
    folders = set_folders(directory)
    for folder in folders:
        files = sorted(
            (f for f in folder.iterdir() if f.is_file() and f.suffix.lower() == ".png"),
            key=lambda f: natural_key(f.stem),
        )
        if not files:
            raise FileFormatError(f"{folder}: no <camera>.png images in this folder")
        view = {}
        for f in files:
            img = grey(read_image(f))
            size = (int(img.shape[1]), int(img.shape[0]))
            if f.stem in sizes and sizes[f.stem] != size:
                w, h = sizes[f.stem]
                raise FileFormatError(
                    f"{f}: {size[0]}×{size[1]} px, but {first[f.stem]} of the same camera "
                    f"is {w}×{h}"
                )
            sizes.setdefault(f.stem, size)
            first.setdefault(f.stem, f)
            view[f.stem] = img
        views.append(view)
    cameras = {n: sizes[n] for n in sorted(sizes, key=natural_key)}
    return ViewSet(tuple(d.name for d in folders), cameras, tuple(views))


def set_images(folder: Path, cameras: tuple[str, ...]) -> dict[str, Path]:
    """The images of one set: ``<camera>.png`` for each camera present in the folder."""
    return {c: folder / f"{c}.png" for c in cameras if (folder / f"{c}.png").exists()}


def write_image(path: str | Path, image: Image) -> None:
    """Write an image as PNG (lossless, 8 or 16 bits), atomically."""
    p = Path(path)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{p}: the image cannot be encoded as PNG")
    tmp = p.with_name(f".{p.name}.tmp")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, p)
