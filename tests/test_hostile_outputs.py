"""Hostile targets and addresses (issue 29): an output that exists and is not a regular
file (a device, a FIFO, a socket, a folder) is refused with one line and left as it
was; a tracker address whose pyserial URL handler writes files (``spy://…?file=``) or
is no plain serial or TCP transport is refused before anything is opened; an image whose
header promises more pixels than an image may take is refused before it is decoded."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from cellcal.errors import FileFormatError, InputError, UserError
from cellcal.files.images import ImageFileError, read_image, write_image
from cellcal.files.models import write_atomically
from tests.test_hostile_inputs import _one_line_exit_2

ROOT = Path(__file__).resolve().parents[1]
JOINTS = "q1,q2,q3,q4,q5,q6\n0,-30,40,0,-20,0\n10,-20,30,5,-10,5\n"


def _fifo(folder: Path) -> Path:
    path = folder / "fifo"
    os.mkfifo(path)
    return path


def _socket(folder: Path) -> Path:
    path = folder / "sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()  # the node stays
    return path


def _device(folder: Path) -> Path:
    if os.geteuid() != 0:
        pytest.skip("mknod needs root (the CI runs as root)")
    path = folder / "full"
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # what /dev/full is
    except PermissionError:
        pytest.skip("this system refuses mknod")
    return path


def _folder(folder: Path) -> Path:
    path = folder / "dir"
    path.mkdir()
    return path


SPECIALS: dict[str, tuple[Callable[[Path], Path], int]] = {
    "fifo": (_fifo, stat.S_IFIFO),
    "socket": (_socket, stat.S_IFSOCK),
    "device": (_device, stat.S_IFCHR),
    "folder": (_folder, stat.S_IFDIR),
}


def _kind(path: Path) -> int:
    return stat.S_IFMT(os.lstat(path).st_mode)


@pytest.fixture(params=sorted(SPECIALS))
def special(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, int]:
    make, kind = SPECIALS[request.param]
    out = tmp_path / "out"
    out.mkdir()
    return make(out), kind


@pytest.mark.timeout(60)
def test_write_atomically_refuses_what_is_not_a_regular_file(special: tuple[Path, int]) -> None:
    path, kind = special
    with pytest.raises(FileFormatError, match=str(path)) as info:
        write_atomically(path, "text")
    assert "\n" not in str(info.value)
    assert _kind(path) == kind  # never replaced
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary left


@pytest.mark.timeout(60)
def test_write_image_refuses_what_is_not_a_regular_file(special: tuple[Path, int]) -> None:
    path, kind = special
    with pytest.raises(InputError, match=str(path)):
        write_image(path, np.zeros((4, 4), np.uint8))
    assert _kind(path) == kind
    assert [p.name for p in path.parent.iterdir()] == [path.name]


@pytest.mark.timeout(60)
def test_a_symlink_to_a_device_is_refused_too(tmp_path: Path) -> None:
    target = _fifo(tmp_path)
    link = tmp_path / "link"
    link.symlink_to(target)
    with pytest.raises(FileFormatError, match="FIFO"):
        write_atomically(link, "text")
    assert link.is_symlink() and _kind(target) == stat.S_IFIFO


def test_write_image_does_not_follow_a_planted_temporary(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (tmp_path / ".cam0.png.tmp").symlink_to(victim)  # the name it used for its temporary
    write_image(tmp_path / "cam0.png", np.zeros((4, 4), np.uint8))
    assert victim.read_text() == "precious"
    assert read_image(tmp_path / "cam0.png").shape == (4, 4)


def test_regular_files_are_still_replaced_whole(tmp_path: Path) -> None:
    path = tmp_path / "model.toml"
    path.write_text("old")
    write_atomically(path, "new")
    assert path.read_text() == "new"
    image = tmp_path / "cam0.png"
    image.write_bytes(b"old")
    write_image(image, np.full((3, 5), 7, np.uint8))
    assert read_image(image).tolist() == np.full((3, 5), 7, np.uint8).tolist()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", ["export", "plan", "predict"])
def test_commands_refuse_an_out_that_is_a_fifo(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, case: str
) -> None:
    fifo = _fifo(tmp_path)
    joints = tmp_path / "joints.csv"
    joints.write_text(JOINTS)
    argv = {
        "export": ["export", "urdf", "--model", "kuka-kr5-arc", "--out", str(fifo)],
        "plan": ["plan", "--mock", "--out", str(fifo)],
        "predict": ["predict", "--model", "kuka-kr5-arc", "--joints", str(joints)],
    }[case]
    if case == "predict":
        argv += ["--out", str(fifo)]
    line = _one_line_exit_2(capsys, *argv)
    assert str(fifo) in line and "FIFO" in line, line
    assert _kind(fifo) == stat.S_IFIFO


@pytest.mark.timeout(60)
def test_export_to_a_device_node_leaves_the_node(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    node = _device(tmp_path)
    line = _one_line_exit_2(capsys, "export", "urdf", "--model", "ur5e", "--out", str(node))
    assert "device" in line, line
    info = os.lstat(node)
    assert stat.S_ISCHR(info.st_mode) and info.st_rdev == os.makedev(1, 7)


# -- tracker addresses -----------------------------------------------------------------


@pytest.mark.timeout(30)
@pytest.mark.parametrize("scheme", ["spy", "SPY", "hwgrep", "alt", "loop", "cp2110"])
def test_tracker_urls_that_write_files_or_are_no_transport_are_refused(
    tmp_path: Path, scheme: str
) -> None:
    from cellcal.drivers.transport import SerialUrlTransport

    victim = tmp_path / "victim"
    victim.write_text("precious")
    url = f"{scheme}://127.0.0.93:9?file={victim}"
    with pytest.raises(UserError, match=f"{scheme.lower()}:// .*refused") as info:
        SerialUrlTransport(url).open()
    assert "\n" not in str(info.value)
    assert victim.read_text() == "precious"


@pytest.mark.timeout(60)
def test_the_tracker_command_refuses_spy_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    victim = tmp_path / "victim"
    victim.write_text("precious")
    url = f"spy://socket://127.0.0.94:9?file={victim}"
    line = _one_line_exit_2(capsys, "tracker", "--url", url, "--timeout", "1")
    assert "spy://" in line and "refused" in line, line
    assert victim.read_text() == "precious"


@pytest.mark.timeout(30)
def test_a_path_that_is_not_a_character_device_is_no_serial_port(tmp_path: Path) -> None:
    from cellcal.drivers.transport import SerialUrlTransport

    plain = tmp_path / "plain"
    plain.write_text("precious")
    with pytest.raises(UserError, match="not a serial device"):
        SerialUrlTransport(str(plain)).open()
    assert plain.read_text() == "precious"


# -- image size before work --------------------------------------------------------------


def _chunk(kind: bytes, data: bytes) -> bytes:
    body = kind + data
    return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))


def _png_bomb(width: int, height: int) -> bytes:
    """A valid grey 8-bit PNG of zeros: a few hundred KB that decode to width × height bytes."""
    z = zlib.compressobj(9)
    row = bytes(width + 1)  # filter byte 0, then the pixels
    parts = [z.compress(row) for _ in range(height)]
    parts.append(z.flush())
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", b"".join(parts))
        + _chunk(b"IEND", b"")
    )


@pytest.mark.timeout(120)
def test_a_png_bomb_is_refused_before_it_is_decoded(tmp_path: Path) -> None:
    path = tmp_path / "bomb.png"
    path.write_bytes(_png_bomb(17000, 17000))  # 289 MB of pixels
    assert path.stat().st_size < 1_000_000
    with pytest.raises(ImageFileError, match=r"17000×17000") as info:
        read_image(path)
    assert "at most" in info.value.reason and "MB" in info.value.reason, info.value.reason


def test_a_png_within_the_bound_is_read(tmp_path: Path) -> None:
    path = tmp_path / "small.png"
    path.write_bytes(_png_bomb(300, 200))
    assert read_image(path).shape == (200, 300)


@pytest.mark.timeout(60)
@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_service_install_refuses_a_fifo_where_the_unit_goes(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    fifo = tmp_path / "cellcal.service"
    os.mkfifo(fifo)  # reading it would wait for a writer forever
    config = ROOT / "config" / "mock-cell-tracker.toml"
    line = _one_line_exit_2(
        capsys, "service", "install", "--config", str(config), "--user", "root",
        "--unit-dir", str(tmp_path),
    )  # fmt: skip
    assert "FIFO" in line, line
    assert _kind(fifo) == stat.S_IFIFO


def _patched_jpeg(width: int, height: int) -> bytes:
    _, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(buf.tobytes())
    at = data.index(b"\xff\xc0")  # the frame header: length, precision, height, width
    data[at + 5 : at + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def _patched_bmp(width: int, height: int) -> bytes:
    _, buf = cv2.imencode(".bmp", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(buf.tobytes())
    data[18:26] = struct.pack("<ii", width, height)
    return bytes(data)


@pytest.mark.parametrize(("name", "data"), [("j.jpg", _patched_jpeg), ("b.bmp", _patched_bmp)])
def test_other_formats_are_sized_from_their_header_too(
    tmp_path: Path, name: str, data: Callable[[int, int], bytes]
) -> None:
    path = tmp_path / name
    path.write_bytes(data(30000, 30000))
    with pytest.raises(ImageFileError, match="30000×30000") as info:
        read_image(path)
    assert "at most" in info.value.reason


@pytest.mark.timeout(120)
def test_a_report_folder_with_a_fifo_in_it_gets_nothing_written(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from cellcal.campaign.runner import start_campaign
    from tests.conftest import tracker_cell

    cell = tracker_cell()
    small = cell.model_copy(
        update={
            "campaign": cell.campaign.model_copy(
                update={"grid": [3, 3, 3], "validation_inside": 4, "validation_per_region": 2}
            )
        }
    )
    db = tmp_path / "c.db"
    start_campaign(small, str(db), config_path=None, mock=True)
    out = tmp_path / "report"
    out.mkdir()
    fifo = out / "poses.csv"  # one of the report's files
    os.mkfifo(fifo)
    line = _one_line_exit_2(capsys, "report", "--db", str(db), "--out", str(out))
    assert "poses.csv" in line and "FIFO" in line, line
    assert [p.name for p in out.iterdir()] == ["poses.csv"]  # nothing written before it
    assert _kind(fifo) == stat.S_IFIFO
