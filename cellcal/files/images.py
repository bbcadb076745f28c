"""Camera images on disk: one image, or sets of images (one folder per set, one image per
camera named ``<camera>.png``), read at the edge with one clear line per fault.

Images are 8- or 16-bit, grey or colour, PNG (what cellcal writes), JPEG, TIFF, BMP,
PNM, WebP or JPEG 2000. A missing, unreadable, truncated or empty file, one that is not
an image, or one whose header promises more than :data:`MAX_DECODED_BYTES` once decoded
(checked before decoding: a small PNG can hold a gigabyte of zeros), is an
:class:`ImageFileError` (a :class:`~cellcal.errors.FileFormatError`) that names it and
says why; OpenCV's own warnings about broken files are kept off the terminal.
"""

from __future__ import annotations

import codecs
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.calib.photogrammetry.marker_corners import grey
from cellcal.errors import FileFormatError, InputError
from cellcal.files.image_headers import image_header
from cellcal.files.outputs import write_atomically

#: Larger image files are refused (a 16-bit 20-megapixel PNG is about 40 MB).
MAX_IMAGE_BYTES = 200 * 1024 * 1024
#: Images that decode to more are refused before they are decoded, from their header
#: (a 20-megapixel 16-bit colour image takes 120 MB, a 150-megapixel grey one 150 MB).
MAX_DECODED_BYTES = 256 * 1024 * 1024

Image = NDArray[Any]


class ImageFileError(FileFormatError):
    """An image file that cannot be used, with the file and the reason apart (a batch
    names it and goes on without it); ``str()`` is ``"<path>: <reason>"``."""

    def __init__(self, path: str | Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = Path(path)
        self.reason = reason


@contextmanager
def _quiet_opencv() -> Iterator[None]:
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


#: The first bytes of the image formats OpenCV reads, to tell a broken image from a file
#: that is not an image at all.
_SIGNATURES = (
    (b"\x89PNG", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"BM", "BMP"),
    (b"\x00\x00\x00\x0cjP  ", "JPEG 2000"),
    (b"\xffO\xffQ", "JPEG 2000"),
)


def _format(head: bytes) -> str | None:
    """The image format whose signature ``head`` (a file's first bytes) starts with."""
    for signature, name in _SIGNATURES:
        if head.startswith(signature):
            return name
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if re.match(rb"P[1-7]\s", head):
        return "PNM"
    return None


def _png_not_whole(data: NDArray[np.uint8]) -> str | None:
    """Why a PNG (by its first bytes) is not whole, from its chunks alone, or None when
    they reach its IEND chunk. Checked before decoding: libpng prints its own complaint
    about a truncated file on the process's stderr."""
    buf = data.data
    if bytes(buf[:8]) != b"\x89PNG\r\n\x1a\n":
        return "damaged PNG"
    pos = 8
    while pos + 12 <= len(buf):
        if bytes(buf[pos + 4 : pos + 8]) == b"IEND":
            return None
        pos += 12 + int.from_bytes(buf[pos : pos + 4], "big")  # length, type, data, CRC
    # the chunks run past the end: cut short, unless the file ends as a PNG does
    return "damaged PNG" if bytes(buf[-8:-4]) == b"IEND" else "truncated PNG"


def _undecodable(data: NDArray[np.uint8]) -> str:
    """Why bytes OpenCV does not decode are no image: a truncated or damaged image of a
    format it reads, a text file, or something else."""
    name = _format(bytes(data[:16]))
    if name == "PNG":
        return f"not a complete image: {_png_not_whole(data) or 'damaged PNG'}"
    if name is not None:
        return f"not a complete image: truncated or damaged {name}"
    sample = bytes(data[:4096])
    try:
        # a multi-byte character cut at the sample's end is no reason to doubt the text
        codecs.getincrementaldecoder("utf-8")().decode(sample, final=False)
    except UnicodeDecodeError:
        return "not an image: no image format OpenCV reads"
    if b"\x00" in sample:
        return "not an image: no image format OpenCV reads"
    return "not an image: a text file"


def read_image(path: str | Path) -> Image:
    """One image as OpenCV decodes it (grey (h, w) or colour (h, w, 3|4); uint8/uint16).
    A file that cannot be used is an :class:`ImageFileError` saying why: missing, empty,
    too large, truncated or damaged, not an image, or pixels of another depth."""
    p = Path(path)
    if not p.exists():
        raise ImageFileError(p, "no such image")
    if not p.is_file():
        raise ImageFileError(p, "not a regular file, not an image")
    size = p.stat().st_size
    if size == 0:
        raise ImageFileError(p, "empty file, not an image")
    if size > MAX_IMAGE_BYTES:
        raise ImageFileError(p, f"{size / 1e6:.0f} MB is too large for an image")
    try:
        data = np.fromfile(p, dtype=np.uint8)
    except OSError as exc:
        raise ImageFileError(p, f"cannot be read ({exc.strerror})") from None
    if bytes(data[:4]) == b"\x89PNG":
        why = _png_not_whole(data)
        if why is not None:
            raise ImageFileError(p, f"not a complete image: {why}")
    _check_decoded_size(p, data)
    try:
        with _quiet_opencv():
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise ImageFileError(p, _undecodable(data))
    if img.dtype not in (np.uint8, np.uint16):
        raise ImageFileError(p, f"{img.dtype} pixels; 8- or 16-bit images expected")
    out: Image = img
    return out


def _check_decoded_size(path: Path, data: NDArray[np.uint8]) -> None:
    """Refuse, before decoding, an image whose header promises more than
    :data:`MAX_DECODED_BYTES`, or whose size its header does not give."""
    header = image_header(data.data)
    if header is None:
        with _quiet_opencv():
            other = _format(bytes(data[:16])) is None and cv2.haveImageReader(str(path))
        if other:
            raise ImageFileError(
                path,
                "its size cannot be read before decoding: an image of another format than "
                "PNG, JPEG, TIFF, BMP, PNM, WebP or JPEG 2000",
            )
        raise ImageFileError(path, _undecodable(data))
    if header.width == 0 or header.height == 0:
        raise ImageFileError(path, f"not a complete image: {header.width}×{header.height} px")
    if header.decoded_bytes > MAX_DECODED_BYTES:
        raise ImageFileError(
            path,
            f"{header.describe()} decode to {header.decoded_bytes / 1e6:.0f} MB; an image "
            f"may take at most {MAX_DECODED_BYTES / 1e6:.0f} MB",
        )


def read_camera_image(path: str | Path, camera: str, size: tuple[int, int]) -> Image:
    """One camera's image, which must be ``size`` (width, height) px as the rig file says;
    any other size is an :class:`ImageFileError`."""
    img = read_image(path)
    h, w = int(img.shape[0]), int(img.shape[1])
    if (w, h) != size:
        raise ImageFileError(
            path, f"{w}×{h} px, but camera {camera} is {size[0]}×{size[1]} in the rig file"
        )
    return img


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


@dataclass(frozen=True)
class Unreadable:
    """An image of a set that was left out: its camera, its file and why."""

    camera: str
    path: Path
    reason: str


def read_set(
    folder: Path, sizes: Mapping[str, tuple[int, int]]
) -> tuple[dict[str, Image], list[Unreadable]]:
    """One set's images: ``<camera>.png`` for each camera of ``sizes`` (name → (width,
    height) px) whose file is in the folder (a camera's image may be missing). A file
    that cannot be read, or is not its camera's size, is left out and named with why."""
    images: dict[str, Image] = {}
    unreadable: list[Unreadable] = []
    for cam, size in sizes.items():
        path = folder / f"{cam}.png"
        if not os.path.lexists(path):
            continue
        try:
            images[cam] = read_camera_image(path, cam, size)
        except ImageFileError as exc:
            unreadable.append(Unreadable(cam, path, exc.reason))
    return images, unreadable


def stray_images(folders: Iterable[Path], cameras: Iterable[str]) -> list[Path]:
    """The ``*.png`` files of the set folders (hidden ones skipped) that are named for
    none of ``cameras``, in natural order."""
    names = {f"{c}.png" for c in cameras}
    return [
        f
        for folder in folders
        for f in sorted(folder.iterdir(), key=lambda f: natural_key(f.name))
        if f.suffix == ".png" and not f.name.startswith(".") and f.name not in names
    ]


def write_image(path: str | Path, image: Image) -> None:
    """Write an image as PNG (lossless, 8 or 16 bits), atomically; an existing ``path``
    that is not a regular file is refused and left as it was (``cellcal.files.outputs``)."""
    p = Path(path)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{p}: the image cannot be encoded as PNG")
    write_atomically(p, buf.tobytes(), durable=False)  # as before: a set is many images
