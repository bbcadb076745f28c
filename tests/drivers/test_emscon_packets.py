"""emScon TPI packets: the golden frames and sizes of the published layout
(``docs/tracker.md``, "emScon"), every packet both ways, and the refusals of bytes that
are not the protocol's."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cellcal.drivers import emscon_packets as p


def test_the_published_frames_byte_for_byte():
    start = bytes.fromhex("0c000000 00000000 31000000")
    assert p.encode_command(p.START_MEASUREMENT) == start
    stationary = bytes.fromhex("14000000 00000000 1c000000 d0070000 01000000")
    assert p.encode_command(p.SET_STATIONARY_MODE_PARAMS, 2000, 1) == stationary
    assert p.decode_command(stationary) == p.Command(p.SET_STATIONARY_MODE_PARAMS, (2000, 1))
    assert p.encode_reply(p.START_MEASUREMENT, p.OK) == bytes.fromhex(
        "10000000 00000000 31000000 00000000"
    )


@pytest.mark.parametrize(
    ("command", "size"),
    [
        (p.GET_SYSTEM_STATUS, 12),
        (p.INITIALIZE, 12),
        (p.SET_UNITS, 32),
        (p.SET_ENVIRONMENT_PARAMS, 36),
        (p.SET_MEASUREMENT_MODE, 16),
        (p.SET_COORDINATE_SYSTEM_TYPE, 16),
        (p.SET_STATIONARY_MODE_PARAMS, 20),
        (p.SET_REFLECTOR, 16),
        (p.SET_SYSTEM_SETTINGS, 48),
        (p.START_MEASUREMENT, 12),
        (p.FIND_REFLECTOR, 20),
        (p.SET_STATISTIC_MODE, 20),
    ],
)
def test_command_sizes(command, size):
    assert p.LAYOUTS[command].command_size == size


@pytest.mark.parametrize(
    ("command", "size"),
    [
        (p.GET_SYSTEM_STATUS, 56),
        (p.GET_MEASUREMENT_STATUS_INFO, 24),
        (p.GET_TRACKER_INFO, 164),
        (p.GET_METEO_STATION_INFO, 92),
        (p.GET_REFLECTORS, 100),
        (p.GET_ENVIRONMENT_PARAMS, 40),
        (p.GET_UNITS, 36),
        (p.SET_UNITS, 16),
        (p.INITIALIZE, 16),
    ],
)
def test_reply_sizes(command, size):
    assert p.LAYOUTS[command].reply_size == size
    assert len(p.encode_reply(command, p.OK)) == size
    # a failing Get* is answered with its full size too, its status set
    failed = p.encode_reply(command, p.SYSTEM_NOT_READY)
    assert len(failed) == size and struct.unpack_from("<i", failed, 12)[0] == 10014


def test_result_sizes_and_fields():
    m = p.Measurement(
        0, (1000.5, -20.25, 300.0), (0.01, 0.02, 0.03), (1e-5, -2e-5, 3e-5), 21.5, 1013.2, 45.0
    )
    nine = p.encode_measurement(m)
    assert len(nine) == 204 and struct.unpack_from("<ii", nine) == (204, 9)
    assert p.decode_packet(nine) == m
    cov = m.covariance()
    assert cov[0, 0] == pytest.approx(1e-4) and cov[1, 2] == cov[2, 1] == 3e-5
    np.testing.assert_array_equal(cov, cov.T)
    # the meteo sits at the end: dTemperature, dPressure, dHumidity
    assert struct.unpack_from("<3d", nine, 180) == (21.5, 1013.2, 45.0)
    two = p.encode_measurement(p.Measurement(0, m.xyz, m.std, None, 21.5, 1013.2, 45.0))
    assert len(two) == 156 and struct.unpack_from("<ii", two) == (156, 2)
    back = p.decode_packet(two)
    assert isinstance(back, p.Measurement) and back.covar is None and back.xyz == m.xyz
    assert struct.unpack_from("<3d", two, 132) == (21.5, 1013.2, 45.0)
    assert back.covariance()[0, 1] == 0.0


def test_events_and_replies_decode():
    assert p.decode_packet(p.encode_error(p.START_MEASUREMENT, 10009)) == p.ErrorPacket(49, 10009)
    assert p.decode_packet(p.encode_status_change(p.MEAS_READY)) == p.StatusChange(27)
    status = p.encode_reply(p.GET_SYSTEM_STATUS, p.OK, 0, 5, 3, 2, 3, 6, 1, 1, 0, 392012)
    reply = p.decode_packet(status)
    assert isinstance(reply, p.Reply) and reply.values[-1] == 392012
    name = p.encode_name("RRR 1.5in")
    assert len(name) == 64 and p.decode_name(name) == "RRR 1.5in"
    refl = p.decode_packet(p.encode_reply(p.GET_REFLECTORS, p.OK, 2, 7, 5, 0.0, name))
    assert isinstance(refl, p.Reply) and p.decode_name(refl.values[4]) == "RRR 1.5in"
    # a failing Get* answered short by a tracker that does so: its status still reads
    short = struct.pack("<iiii", 16, 0, p.GET_SYSTEM_STATUS, 10014)
    assert p.decode_packet(short) == p.Reply(1, 10014, ())


@pytest.mark.parametrize(
    ("data", "what"),
    [
        (struct.pack("<ii", 3, 0), "announces 3 bytes"),
        (struct.pack("<ii", 1 << 20, 2), "announces 1048576"),
        (struct.pack("<iiii", 16, 2, 0, 0), "type 2 packet of 16 bytes"),
        (struct.pack("<iii", 12, 42, 0), "unknown type 42"),
        (struct.pack("<iiii", 16, 0, 9999, 0), "command 9999"),
        (p.encode_reply(p.GET_SYSTEM_STATUS, p.OK)[:40], "of 40 bytes announces 56"),
        (struct.pack("<iiii", 16, 0, p.GET_SYSTEM_STATUS, 0), "GetSystemStatus reply of 16"),
    ],
)
def test_bytes_that_are_not_a_packet(data, what):
    with pytest.raises(p.PacketError, match=what):
        p.decode_packet(data)


def test_commands_a_server_refuses():
    with pytest.raises(p.PacketError, match="SetUnits of 28 bytes"):
        p.decode_command(p.encode_command(p.SET_UNITS, 1, 1, 0, 1, 0)[:28])
    with pytest.raises(p.PacketError, match="not one this tracker serves"):
        p.decode_command(struct.pack("<iii", 12, 0, 10))
    with pytest.raises(p.PacketError, match="not a command"):
        p.decode_command(p.encode_status_change(27))
    with pytest.raises(p.PacketError, match="SetUnits"):
        p.encode_command(p.SET_UNITS, 1, 2)
