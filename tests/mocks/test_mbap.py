"""The Modbus/TCP codec of the twins (cellcal/mocks/modbus/mbap.py), without sockets: frames cut
out of a byte stream however the reads split or join them, bad length fields, and the
request checks of the spec (function code → 1, quantities and byte counts → 3)."""

from __future__ import annotations

import struct

import pytest

from cellcal.mocks.modbus.mbap import (
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    Frame,
    ModbusError,
    Request,
    decode_request,
    encode_frame,
    exception_pdu,
    reply_pdu,
    split_frames,
)

READ = bytes.fromhex("0300010004")  # read holding registers 1..4
WRITE = bytes.fromhex("10008200020400010009")  # write 130..131 = 1, 9


def test_a_frame_round_trips():
    frame = encode_frame(0x1234, 7, READ)
    assert frame == bytes.fromhex("123400000006070300010004")
    split = split_frames(frame)
    assert split.frames == (Frame(0x1234, 0, 7, READ),) and split.rest == b""
    assert split.error is None


def test_frames_are_cut_out_of_any_split_of_the_stream():
    stream = encode_frame(1, 1, READ) + encode_frame(2, 1, WRITE) + encode_frame(3, 9, b"\x41")
    want = [Frame(1, 0, 1, READ), Frame(2, 0, 1, WRITE), Frame(3, 0, 9, b"\x41")]
    for cuts in ([], [1], [5, 6, 7], [12], [13, 30], list(range(1, len(stream)))):
        got: list[Frame] = []
        rest = b""
        for lo, hi in zip([0, *cuts], [*cuts, len(stream)], strict=True):
            split = split_frames(rest + stream[lo:hi])
            assert split.error is None
            got += split.frames
            rest = split.rest
        assert got == want and rest == b"", cuts


def test_a_partial_frame_waits_for_the_rest():
    frame = encode_frame(5, 1, WRITE)
    for n in range(len(frame)):
        split = split_frames(frame[:n])
        assert split.frames == () and split.rest == frame[:n] and split.error is None
    split = split_frames(frame + frame[:3])
    assert len(split.frames) == 1 and split.rest == frame[:3]


def test_another_protocol_id_is_still_delimited_by_its_length():
    other = encode_frame(8, 1, b"\xff" * 20, protocol=0x1234)
    split = split_frames(other + encode_frame(9, 1, READ))
    assert [(f.transaction, f.protocol) for f in split.frames] == [(8, 0x1234), (9, 0)]
    assert split.frames[0].pdu == b"\xff" * 20 and split.error is None


@pytest.mark.parametrize("length", [0, 1, 255, 0x1000, 0xFFFF])
def test_a_length_outside_2_to_254_is_a_framing_error(length):
    good = encode_frame(1, 1, READ)
    bad = struct.pack(">HHH", 2, 0, length)  # known bad as soon as the length is there
    split = split_frames(good + bad)
    assert split.frames == (Frame(1, 0, 1, READ),)
    assert split.error is not None and str(length) in split.error
    assert split_frames(bad[:5]).error is None  # not yet known


def test_the_largest_frame_is_accepted():
    pdu = bytes([3]) + bytes(252)  # 253 bytes: length 254
    split = split_frames(encode_frame(1, 1, pdu))
    assert split.frames[0].pdu == pdu and split.error is None


def test_requests_decode():
    assert decode_request(READ) == Request(3, read_address=1, read_count=4)
    assert decode_request(b"\x04\x00\x0a\x00\x7d") == Request(4, read_address=10, read_count=125)
    assert decode_request(b"\x06\x00\x82\x00\x03") == Request(6, write_address=130, values=(3,))
    assert decode_request(WRITE) == Request(16, write_address=130, values=(1, 9))
    rw = struct.pack(">BHHHHB2H", 23, 0, 4, 130, 2, 4, 1, 9)
    assert decode_request(rw) == Request(23, 0, 4, 130, (1, 9))
    most = struct.pack(">BHHB123H", 16, 0, 123, 246, *range(123))
    assert decode_request(most).values == tuple(range(123))


@pytest.mark.parametrize(
    ("pdu", "code"),
    [
        (b"\x41\x00\x00", ILLEGAL_FUNCTION),
        (b"\x01\x00\x00\x00\x01", ILLEGAL_FUNCTION),  # coils
        (b"\x02\x00\x00\x00\x01", ILLEGAL_FUNCTION),  # discrete inputs
        (b"\x05\x00\x00\xff\x00", ILLEGAL_FUNCTION),
        (b"\x0f\x00\x00\x00\x01\x01\x01", ILLEGAL_FUNCTION),
        (b"\x2b\x0e\x01\x00", ILLEGAL_FUNCTION),  # device identification
        (b"\x03\x00\x00\x00\x00", ILLEGAL_VALUE),  # read 0
        (b"\x03\x00\x00\x00\x7e", ILLEGAL_VALUE),  # read 126
        (b"\x03\x00\x00\x00", ILLEGAL_VALUE),  # too short
        (b"\x03\x00\x00\x00\x01\x00", ILLEGAL_VALUE),  # too long
        (b"\x06\x00\x00", ILLEGAL_VALUE),
        (b"\x10\x00\x00\x00\x00\x00", ILLEGAL_VALUE),  # write 0
        (b"\x10\x00\x00\x00\x7c\xf8", ILLEGAL_VALUE),  # write 124
        (b"\x10\x00\x00\x00\x02\x03\x00\x00\x00", ILLEGAL_VALUE),  # byte count 3 for 2
        (b"\x10\x00\x00\x00\x01\x02\x00", ILLEGAL_VALUE),  # a byte missing
        (b"\x10\x00\x00", ILLEGAL_VALUE),
        (struct.pack(">BHHHHB", 23, 0, 0, 130, 1, 2) + b"\0\0", ILLEGAL_VALUE),  # read 0
        (struct.pack(">BHHHHB", 23, 0, 126, 130, 1, 2) + b"\0\0", ILLEGAL_VALUE),  # read 126
        (struct.pack(">BHHHHB", 23, 0, 1, 130, 122, 244) + bytes(244), ILLEGAL_VALUE),  # write 122
        (struct.pack(">BHHHHB", 23, 0, 1, 130, 1, 4) + bytes(4), ILLEGAL_VALUE),  # byte count
    ],
)
def test_bad_requests_raise_the_spec_exception_code(pdu, code):
    with pytest.raises(ModbusError) as err:
        decode_request(pdu)
    assert err.value.code == code


def test_replies_encode():
    assert reply_pdu(Request(3, 1, 2), [0x1234, 5]) == bytes.fromhex("030412340005")
    assert reply_pdu(Request(4, 1, 1), [7]) == bytes.fromhex("04020007")
    assert reply_pdu(Request(6, write_address=130, values=(3,)), []) == bytes.fromhex("0600820003")
    assert reply_pdu(Request(16, write_address=130, values=(1, 9)), []) == bytes.fromhex(
        "1000820002"
    )
    assert reply_pdu(Request(23, 3, 1, 130, (1, 9)), [9]) == bytes.fromhex("17020009")
    assert exception_pdu(3, 3) == b"\x83\x03" and exception_pdu(0x41, 1) == b"\xc1\x01"
    assert exception_pdu(16, 0x0B) == b"\x90\x0b"
