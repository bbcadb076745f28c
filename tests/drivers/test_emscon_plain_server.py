"""cellcal's emScon driver against an emScon server it did not make
(``tests/independent/emscon_server.py``: written from the published layout, with its own
choices — short failing Get* replies, a beam lost until searched, metres or millimetres),
over real sockets on 127.0.0.28 and .29."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from cellcal.drivers.emscon import EmsconOptions, EmsconTracker
from cellcal.errors import DeviceError
from tests.independent.emscon_server import PlainEmscon

pytestmark = [pytest.mark.slow, pytest.mark.timeout(60)]

POSITION = [3120.5, -410.25, 655.0]
COV = [[9e-4, 2e-4, -1e-4], [2e-4, 4e-4, 5e-5], [-1e-4, 5e-5, 2.5e-4]]


@contextmanager
def plain(host: str, **kwargs: object) -> Iterator[PlainEmscon]:
    server = PlainEmscon(host, POSITION, COV, **kwargs)  # listening once constructed
    try:
        yield server
    finally:
        server.close()


def _tracker(server: PlainEmscon, **options: object) -> EmsconTracker:
    host, port = server.address
    return EmsconTracker(EmsconOptions(name="t", address=f"{host}:{port}", **options))


def test_the_driver_measures_from_a_server_it_did_not_make():
    with plain("127.0.0.28", cold_for=1) as server:
        t = _tracker(server, reflector="CCR-0.5in")
        t.connect()  # through a warm-up and an initialisation
        try:
            d = t.describe()
            assert (d.model, d.serial, d.firmware) == ("AT402", "7001", "3.5.100")
            s = t.measure(4, 1.0)
        finally:
            t.close()
        assert server.units[0] == 1  # millimetres asked for, and got
        assert 40 in server.seen and server.initialized
    np.testing.assert_allclose(s.xyz, [POSITION] * 4)
    assert s.cov is not None and np.allclose(s.cov, [COV] * 4)
    assert s.meteo is not None and np.allclose(s.meteo, [[21.25, 1008.5, 37.0]] * 4)


def test_a_beam_lost_until_searched_and_a_second_client():
    with plain("127.0.0.29", break_on={2, 5}) as server:
        t = _tracker(server, relock="find-reflector", beam_wait_s=2.0)
        t.connect()
        try:
            with pytest.raises(DeviceError, match="another client is connected"):
                _tracker(server).connect()
            s = t.measure(5, 1.0)
        finally:
            t.close()
        assert server.seen.count(63) == 2  # FindReflector after each break
    assert s.n == 5 and s.retries == 2 and "7 attempts" in s.note


def test_a_beam_that_waiting_does_not_bring_back_ends_the_series():
    """This server never relocks by itself: ``relock = "wait"`` gives up after
    beam_wait_s and the series keeps what it has."""
    with plain("127.0.0.29", break_on={3}) as server:
        t = _tracker(server, relock="wait", beam_wait_s=0.3)
        t.connect()
        try:
            s = t.measure(5, 1.0)
        finally:
            t.close()
    assert s.n == 2 and "no reflector found 0.3 s after the beam broke" in s.note
