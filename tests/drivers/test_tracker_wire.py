"""The tracker driver, request by request, against a scripted wire."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellcal.clock import SimulatedClock
from cellcal.drivers.tracker import Environment, LineTracker
from cellcal.drivers.tracker_protocol import (
    BeamBrokenError,
    End,
    Err,
    Evt,
    Garbage,
    MeteoOutOfRangeError,
    Ok,
    Point,
    TrackerBadParameterError,
    TrackerBusyError,
    TrackerError,
    TrackerNotInitializedError,
    TrackerTimeoutError,
    TrackerUnknownCommandError,
    parse_line,
)
from tests.drivers.scripted import ScriptedTransport

HANDSHAKE = [("*IDN?", ["OK Leica,AT960,SN-12,2.4"]), ("INIT", ["OK"])]


def tracker(pairs, **kw):
    t = ScriptedTransport(HANDSHAKE + pairs, drop_at=kw.pop("drop_at", None))
    lt = LineTracker("tracker", "scripted://", transport=t, timeout=0.2, backoff_s=0.0, **kw)
    lt.connect()
    return lt, t


def test_handshake_and_every_request():
    lt, t = tracker(
        [
            ("STAT?", ["OK ready=1 beam=1 meteo=0 init=1"]),
            ("ENV?", ["OK T=20.5 P=1012.00 RH=40"]),
            ("ENV T=21.00 P=1013.25 RH=45.0", ["OK"]),
            ("SMR?", ["OK RRR15"]),
            ("SMR RRR05", ["OK"]),
            ("INIT", ["OK"]),
        ]
    )
    assert lt.identity.maker == "Leica" and lt.identity.serial == "SN-12"
    s = lt.status()
    assert (s.ready, s.beam, s.meteo, s.init) == (True, True, False, True)
    assert lt.environment() == Environment(20.5, 1012.0, 40.0)
    lt.set_environment(Environment(21.0, 1013.25, 45.0))
    assert lt.reflector() == "RRR15"
    lt.set_reflector("RRR05")
    lt.initialise()
    assert t.done and t.written[:2] == ["*IDN?", "INIT"]


def test_configured_reflector_and_environment_are_set_at_connect():
    t = ScriptedTransport(
        [*HANDSHAKE, ("SMR TBR05", ["OK"]), ("ENV T=19.50 P=990.00 RH=30.0", ["OK"])]
    )
    lt = LineTracker(
        "t",
        "scripted://",
        transport=t,
        timeout=0.2,
        reflector="TBR05",
        environment=Environment(19.5, 990.0, 30.0),
    )
    lt.connect()
    assert t.done


def test_measure_with_events_anywhere_and_timestamps():
    clock = SimulatedClock(start=100.0)
    lt, _ = tracker(
        [
            (
                "MEAS 3 10",
                [
                    "EVT TEMP 20.1",
                    "OK 3",
                    "PT 0 12.100 1048.6201 29.9440 875.0770",
                    "EVT BEAM OK",
                    "PT 1 12.200 1048.6199 29.9442 875.0768",
                    "PT 2 12.300 1048.6200 29.9441 875.0769",
                    "END 3",
                ],
            )
        ],
        clock=clock,
    )
    s = lt.measure(3, 10.0)
    np.testing.assert_allclose(s.xyz[1], [1048.6199, 29.9442, 875.0768])
    np.testing.assert_allclose(s.device_time, [12.1, 12.2, 12.3])
    np.testing.assert_allclose(s.host_time, 100.0)
    assert [e.name for _, e in lt.events] == ["TEMP", "BEAM"]
    assert lt.garbage == 0 and s.retries == 0


def test_garbage_is_counted_never_data():
    lt, _ = tracker(
        [
            (
                "MEAS 2 10",
                [
                    b"\xff\xfe\x00binary",
                    "OK 2",
                    "PT 0 1.0 1 2 3",
                    "PT 7 1.1 9 9 9",  # wrong index: not data
                    "PT 1 1.1 x y z",  # malformed: not data
                    "hello",
                    "PT 1 1.2 4 5 6",
                    "END 2",
                ],
            )
        ]
    )
    s = lt.measure(2, 10.0)
    np.testing.assert_array_equal(s.xyz, [[1, 2, 3], [4, 5, 6]])
    assert lt.garbage == 4


def test_beam_broken_mid_series_keeps_points_waits_and_completes():
    lt, t = tracker(
        [
            (
                "MEAS 4 10",
                ["OK 4", "PT 0 1.0 1 1 1", "PT 1 1.1 2 2 2", "EVT BEAM LOST", "ERR 40 BEAM_BROKEN"],
            ),
            ("STAT?", ["OK ready=1 beam=0 meteo=1 init=1"]),
            (None, ["EVT BEAM OK"]),
            ("MEAS 2 10", ["OK 2", "PT 0 2.0 3 3 3", "PT 1 2.1 4 4 4", "END 2"]),
        ],
        beam_wait_s=2.0,
    )
    s = lt.measure(4, 10.0)
    np.testing.assert_array_equal(s.xyz[:, 0], [1, 2, 3, 4])
    np.testing.assert_allclose(s.device_time, [1.0, 1.1, 2.0, 2.1])
    assert s.retries == 1 and t.done


def test_beam_broken_too_often_returns_what_was_kept_and_says_why():
    broken = ["OK 3", "PT 0 1.0 1 1 1", "ERR 40 BEAM_BROKEN"]
    lt, t = tracker(
        [
            ("MEAS 3 10", broken),
            ("STAT?", ["OK ready=1 beam=1 meteo=1 init=1"]),
            ("MEAS 2 10", ["ERR 40 BEAM_BROKEN"]),
        ],
        beam_retries=1,
    )
    s = lt.measure(3, 10.0)
    assert s.n == 1 and s.retries == 1 and t.done
    assert s.note == (
        "1 of 3 samples after 3 attempts (2 failed): beam broken 2 times, beam_retries is 1; "
        "beam broken after 1 of 3 points; beam broken after 0 of 2 points"
    )


def test_a_beam_broken_before_any_point_is_no_target():
    lt, _ = tracker([("MEAS 3 10", ["ERR 40 BEAM_BROKEN"])], beam_retries=0)
    with pytest.raises(BeamBrokenError, match="beam broken 1 times; 0 of 3 points kept"):
        lt.measure(3, 10.0)


def test_garbled_points_are_taken_again_until_there_are_n():
    lt, t = tracker(
        [
            (
                "MEAS 3 10",
                ["OK 3", "PT 0 1.0 1 1 1", "PT 1 1.1 x y z", "PT 2 1.2 3 3 3", "END 3"],
            ),
            # PT 1 came garbled, so PT 2 is out of order: both are taken again
            ("MEAS 2 10", ["OK 2", "PT 0 2.0 4 4 4", "PT 1 2.1 5 5 5", "END 2"]),
        ]
    )
    s = lt.measure(3, 10.0)
    np.testing.assert_array_equal(s.xyz[:, 0], [1, 4, 5])
    np.testing.assert_allclose(s.device_time, [1.0, 2.0, 2.1])
    assert s.retries == 1 and lt.garbage == 2 and t.done
    assert s.note == "3 of 3 samples after 5 attempts (2 failed): 2 of 3 points garbled"


def test_re_takes_stop_at_twice_n_attempts_and_keep_what_they_have():
    lt, t = tracker(
        [
            ("MEAS 2 10", ["OK 2", "PT 0 1.0 1 1 1", "PT 1 garbled", "END 2"]),
            ("MEAS 1 10", ["OK 1", "PT 0 garbled", "END 1"]),
            ("MEAS 1 10", ["OK 1", "END 0"]),
        ]
    )
    s = lt.measure(2, 10.0)
    assert s.n == 1 and s.retries == 2 and t.done  # 1 kept + 3 failed = 4 attempts: no more
    assert s.note == (
        "1 of 2 samples after 4 attempts (3 failed): 1 of 2 points garbled; 1 of 1 points "
        "garbled; series ended after 0 of 1 points"
    )


def test_an_end_that_counts_fewer_points_than_were_sent_is_a_fault():
    lt, _ = tracker([("MEAS 2 10", ["OK 2", "PT 0 1.0 1 1 1", "PT 1 1.1 2 2 2", "END 1"])])
    with pytest.raises(TrackerError, match="END 1 after 2 points"):
        lt.measure(2, 10.0)


def test_dropped_link_reconnects_and_carries_on():
    meas = ("MEAS 2 10", ["OK 2", "PT 0 1.0 1 1 1", "PT 1 1.1 2 2 2", "END 2"])
    # The first MEAS write fails (the link is down): reconnect, handshake again, MEAS.
    lt, t = tracker([*HANDSHAKE, meas], drop_at=3)
    s = lt.measure(2, 10.0)
    assert s.n == 2 and s.retries == 1 and lt.reconnections == 1 and t.opened == 2


def test_timeout_on_every_request():
    lt, _ = tracker([("STAT?", []), *HANDSHAKE, ("STAT?", [])])
    with pytest.raises(TrackerTimeoutError, match="no answer to 'STAT\\?'"):
        lt.status()
    assert lt.reconnections == 1


@pytest.mark.parametrize(
    ("reply", "error"),
    [
        ("ERR 1 BUSY", TrackerBusyError),
        ("ERR 3 BAD_PARAMETER line too long", TrackerBadParameterError),
        ("ERR 4 UNKNOWN_COMMAND", TrackerUnknownCommandError),
        ("ERR 39 NOT_INITIALIZED", TrackerNotInitializedError),
        ("ERR 57 METEO_OUT_OF_RANGE", MeteoOutOfRangeError),
    ],
)
def test_error_codes_become_exceptions(reply, error):
    lt, _ = tracker([("ENV T=50.00 P=1013.00 RH=40.0", [reply])])
    with pytest.raises(error, match=reply.split()[2]):
        lt.set_environment(Environment(50.0, 1013.0, 40.0))


def test_parse_line_examples():
    assert parse_line(b"OK") == Ok("")
    assert parse_line(b"OK cellcal,mock,1,2") == Ok("cellcal,mock,1,2")
    assert parse_line(b"ERR 40 BEAM_BROKEN") == Err(40, "BEAM_BROKEN", "")
    assert parse_line(b"ERR 3 BAD_PARAMETER line too long") == Err(
        3, "BAD_PARAMETER", "line too long"
    )
    assert parse_line(b"EVT BEAM LOST") == Evt("BEAM", "LOST")
    assert parse_line(b"PT 2 12.3 -1.5e2 .5 7") == Point(2, 12.3, -150.0, 0.5, 7.0)
    assert parse_line(b"END 20") == End(20)
    for bad in (b"ok", b"ERR x BUSY", b"PT 1 2 3 4", b"PT 1 nan 1 2 3", b"OK\x00", b"\xc3\xa9"):
        assert isinstance(parse_line(bad), Garbage)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_hostile_lines_never_escape_the_parser(raw):
    msg = parse_line(raw.replace(b"\n", b""))
    assert isinstance(msg, Ok | Err | Evt | Point | End | Garbage)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=80).filter(lambda b: b"\n" not in b), max_size=8))
def test_hostile_lines_in_a_series_are_never_data(noise):
    lines = ["OK 2", "PT 0 1.0 1 2 3"] + [
        n for n in noise if not n.startswith((b"PT", b"END", b"ERR", b"OK"))
    ]
    lt, _ = tracker([("MEAS 2 10", [*lines, "PT 1 1.1 4 5 6", "END 2"])])
    s = lt.measure(2, 10.0)
    np.testing.assert_array_equal(s.xyz, [[1, 2, 3], [4, 5, 6]])


class _Chatty(ScriptedTransport):
    """After its script, the peer keeps the link alive with events but never finishes."""

    def read(self, max_bytes, timeout):
        data = super().read(max_bytes, timeout)
        if data or self.pairs:
            return data
        time.sleep(min(timeout, 0.01))
        return b"EVT TEMP 20.0\n"


@pytest.mark.timeout(60)
def test_a_peer_that_talks_but_never_finishes_a_series_meets_the_overall_deadline():
    t = _Chatty([*HANDSHAKE, ("MEAS 2 10", ["OK 2", "PT 0 1.0 1 1 1"])])
    lt = LineTracker(
        "tracker", "scripted://", transport=t, timeout=0.2, backoff_s=0.0, reconnects=0
    )
    lt.connect()
    with pytest.raises(TrackerTimeoutError, match="not finished within"):
        lt.measure(2, 10.0)
    assert len(lt.events) > 10  # it kept talking the whole time
