"""What an image file will take once decoded, read from its header alone.

A compressed image is small on disk and large in memory: a PNG of a few hundred KB can
decode to a gigabyte of zeros. The header says how many pixels, channels and bits the
decoder will allocate, so the size is known before any decoding: PNG (IHDR), JPEG (the
frame header), TIFF (the first image), BMP, PNM, WebP and JPEG 2000 are read here, and
an image of another format is not decoded at all (``imagefiles.read_image``).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass


@dataclass(frozen=True)
class ImageHeader:
    """An image's size as its header gives it: pixels, and the channels and bytes per
    channel the decoder returns (at most: a palette may come out as four channels)."""

    width: int
    height: int
    channels: int
    bytes_per_channel: int

    @property
    def decoded_bytes(self) -> int:
        return self.width * self.height * self.channels * self.bytes_per_channel

    def describe(self) -> str:
        bits = 8 * self.bytes_per_channel
        return f"{self.width}×{self.height} px, {self.channels} channel(s) of {bits} bits"


def _png(head: bytes) -> ImageHeader | None:
    # signature (8), then the IHDR chunk: length (4), "IHDR", width, height, depth, colour
    if len(head) < 26 or head[12:16] != b"IHDR":
        return None
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    channels = {0: 1, 2: 3, 3: 4, 4: 4, 6: 4}.get(colour, 4)  # grey+alpha, palette: BGRA
    return ImageHeader(width, height, channels, 2 if depth > 8 else 1)


#: The JPEG frame headers (SOF0..SOF15 less DHT, JPG and DAC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg(data: memoryview) -> ImageHeader | None:
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if marker in _SOF and pos + 10 <= len(data):
            precision, height, width, components = struct.unpack(">BHHB", data[pos + 4 : pos + 10])
            if height == 0:  # the height comes later (DNL), which OpenCV does not read
                return None
            return ImageHeader(width, height, max(components, 1), 2 if precision > 8 else 1)
        if marker == 0xDA:  # scan data before any frame header
            return None
        pos += 2 + length
    return None


def _bmp(head: bytes) -> ImageHeader | None:
    if len(head) < 30:
        return None
    (size,) = struct.unpack("<I", head[14:18])
    if size == 12:  # OS/2 header: 16-bit sizes
        width, height = struct.unpack("<HH", head[18:22])
    else:
        width, height = struct.unpack("<ii", head[18:26])
    return ImageHeader(abs(width), abs(height), 4, 1)


def _pnm(head: bytes) -> ImageHeader | None:
    text = re.sub(rb"#[^\n]*\n", b" ", head[:1024])
    m = re.match(rb"P([1-7])\s+(\d+)\s+(\d+)(?:\s+(\d+))?", text)
    if m is None or m.group(1) == b"7":  # PAM: WIDTH/HEIGHT lines
        m7 = re.search(rb"WIDTH\s+(\d+).*?HEIGHT\s+(\d+)", text, re.S)
        if m7 is None:
            return None
        return ImageHeader(int(m7.group(1)), int(m7.group(2)), 4, 2)
    kind = int(m.group(1))
    channels = 3 if kind in (3, 6) else 1
    maxval = int(m.group(4)) if m.group(4) and kind not in (1, 4) else 255
    return ImageHeader(int(m.group(2)), int(m.group(3)), channels, 2 if maxval > 255 else 1)


def _tiff(data: memoryview) -> ImageHeader | None:
    order = "<" if bytes(data[:2]) == b"II" else ">"
    if len(data) < 8:
        return None
    (ifd,) = struct.unpack(order + "I", data[4:8])
    if ifd + 2 > len(data):
        return None
    (count,) = struct.unpack(order + "H", data[ifd : ifd + 2])
    tags: dict[int, int] = {}
    for k in range(min(count, 512)):
        at = ifd + 2 + 12 * k
        if at + 12 > len(data):
            break
        tag, kind, n = struct.unpack(order + "HHI", data[at : at + 8])
        if kind == 3:  # SHORT: the first value, in the entry itself
            (value,) = struct.unpack(order + "H", data[at + 8 : at + 10])
        elif kind == 4:  # LONG
            (value,) = struct.unpack(order + "I", data[at + 8 : at + 12])
        else:
            continue
        if tag == 258 and n > 2 and kind == 3:  # BitsPerSample: an offset to n values
            (offset,) = struct.unpack(order + "I", data[at + 8 : at + 12])
            if offset + 2 <= len(data):
                (value,) = struct.unpack(order + "H", data[offset : offset + 2])
        tags[tag] = value
    if 256 not in tags or 257 not in tags:
        return None
    channels = max(tags.get(277, 1), 1)
    bits = max(tags.get(258, 8), 1)
    return ImageHeader(tags[256], tags[257], channels, -(-bits // 8))


def _webp(head: bytes) -> ImageHeader | None:
    kind = head[12:16]
    if kind == b"VP8X" and len(head) >= 30:
        width = int.from_bytes(head[24:27], "little") + 1
        height = int.from_bytes(head[27:30], "little") + 1
    elif kind == b"VP8 " and len(head) >= 30:
        width = int.from_bytes(head[26:28], "little") & 0x3FFF
        height = int.from_bytes(head[28:30], "little") & 0x3FFF
    elif kind == b"VP8L" and len(head) >= 25:
        bits = int.from_bytes(head[21:25], "little")
        width = (bits & 0x3FFF) + 1
        height = ((bits >> 14) & 0x3FFF) + 1
    else:
        return None
    return ImageHeader(width, height, 4, 1)


def _jpeg2000(head: bytes) -> ImageHeader | None:
    at = head.find(b"ihdr")  # a JP2 file: the image header box
    if at >= 0 and at + 15 <= len(head):
        height, width, components, depth = struct.unpack(">IIHB", head[at + 4 : at + 15])
        return ImageHeader(width, height, max(components, 1), 2 if (depth & 0x7F) >= 8 else 1)
    at = head.find(b"\xff\x4f\xff\x51")  # a bare codestream: SOC, then SIZ
    if at < 0 or at + 44 > len(head):
        return None
    x, y, x0, y0 = struct.unpack(">IIII", head[at + 8 : at + 24])
    (components,) = struct.unpack(">H", head[at + 40 : at + 42])
    depth = head[at + 42] & 0x7F
    return ImageHeader(max(x - x0, 0), max(y - y0, 0), max(components, 1), 2 if depth >= 8 else 1)


def image_header(data: bytes | memoryview) -> ImageHeader | None:
    """The header of the image whose file's bytes are ``data``, or None for a format not
    read here or a header cut short."""
    whole = memoryview(data).cast("B")
    head = bytes(whole[:1024])
    try:
        if head.startswith(b"\x89PNG\r\n\x1a\n"):
            return _png(head)
        if head.startswith(b"\xff\xd8\xff"):
            return _jpeg(whole)
        if head.startswith(b"BM"):
            return _bmp(head)
        if head.startswith((b"II*\x00", b"MM\x00*")):
            return _tiff(whole)
        if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
            return _webp(head)
        if head.startswith((b"\x00\x00\x00\x0cjP  ", b"\xffO\xffQ")):
            return _jpeg2000(head)
        if re.match(rb"P[1-7]\s", head):
            return _pnm(head)
    except (struct.error, ValueError):
        return None
    return None
