"""One contract every tracker backend must pass, and the driver against the protocol-level
mock with each fault injected — over TCP (127.0.0.x) and over a pseudo-terminal."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.clock import SimulatedClock
from cellcal.commands.mock import simulated_cell_of
from cellcal.drivers.tracker import Environment, LineTracker
from cellcal.drivers.tracker_protocol import (
    MeteoOutOfRangeError,
    TrackerBadParameterError,
)
from cellcal.drivers.transport import TransportError
from cellcal.errors import DeviceError
from cellcal.mocks.tracker.server import TrackerFaults, TrackerTwin

pytestmark = pytest.mark.twin

TRUTH = np.array([2100.0, -350.0, 640.0])
NOISE = 0.01


class Target:
    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def sample(self, n: int) -> np.ndarray:
        self.calls += 1
        return TRUTH + self.rng.normal(0, NOISE, (n, 3))


def _backend(kind: str, faults: TrackerFaults | None = None, **kw):
    server = TrackerTwin(Target(), faults=faults or TrackerFaults())
    if kind == "tcp":
        host, port = server.start_tcp("127.0.0.5", 0)
        url = f"socket://{host}:{port}"
    else:
        url = server.start_pty()
    kw.setdefault("timeout", 2.0)
    kw.setdefault("backoff_s", 0.01)
    tracker = LineTracker("t", url, clock=SimulatedClock(start=50.0), **kw)
    return server, tracker


BACKENDS = ["tcp", "pty"]


@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", BACKENDS)
def test_contract(kind):
    """What the engine and the CLI rely on, whatever the transport."""
    server, t = _backend(kind)
    with server:
        t.connect()
        try:
            assert t.identity.model == "mock-tracker" and t.identity.serial == "SIM-0001"
            st = t.status()
            assert st.ready and st.beam and st.init
            t.set_environment(Environment(21.5, 1001.0, 40.0))
            assert t.environment() == Environment(21.5, 1001.0, 40.0)
            t.set_reflector("RRR05")
            assert t.reflector() == "RRR05"
            s = t.measure(20, 10.0)
            assert s.n == 20 and s.sensor == "t" and s.retries == 0
            np.testing.assert_allclose(s.mean, TRUTH, atol=5 * NOISE)
            np.testing.assert_allclose(np.diff(s.device_time), 0.1, atol=1e-6)
            np.testing.assert_allclose(s.host_time, 50.0)  # the driver's clock, on receipt
            with pytest.raises(MeteoOutOfRangeError):
                t.set_environment(Environment(55.0, 1001.0, 40.0))
            with pytest.raises(TrackerBadParameterError):
                t.set_reflector("RRR99")
            with pytest.raises(TrackerBadParameterError):
                t.measure(0, 10.0)
            assert t.garbage == 0
        finally:
            t.close()


@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", BACKENDS)
def test_beam_break_mid_series_keeps_points_and_completes(kind):
    server, t = _backend(kind, TrackerFaults(beam_break_after=7, beam_breaks=2), beam_wait_s=5)
    with server:
        t.connect()
        s = t.measure(20, 10.0)
        t.close()
    assert s.n == 20 and s.retries == 2
    np.testing.assert_allclose(s.mean, TRUTH, atol=5 * NOISE)
    assert any(e.name == "BEAM" for _, e in t.events)


@pytest.mark.timeout(30)
def test_beam_broken_too_often_keeps_what_it_has_and_says_why():
    server, t = _backend("tcp", TrackerFaults(beam_break_after=3, beam_breaks=10), beam_retries=2)
    with server:
        t.connect()
        s = t.measure(20, 10.0)
        # breaks after 3 of 20, 3 of 17, 3 of 14: one more than beam_retries
        assert s.n == 9 and s.retries == 2
        assert s.note.startswith(
            "9 of 20 samples after 12 attempts (3 failed): beam broken 3 times, beam_retries is 2"
        )
        t.close()


@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", BACKENDS)
def test_garbage_and_events_are_never_data(kind):
    server, t = _backend(kind, TrackerFaults(garbage_every=3, event_every=2))
    with server:
        t.connect()
        s = t.measure(30, 10.0)
        t.close()
    assert s.n == 30
    assert np.abs(s.xyz - TRUTH).max() < 10 * NOISE
    assert t.garbage >= 5 and len(t.events) >= 1


@pytest.mark.timeout(30)
def test_slow_replies_within_and_beyond_the_timeout():
    server, t = _backend("tcp", TrackerFaults(reply_delay_s=0.2), timeout=1.0)
    with server:
        t.connect()
        assert t.measure(5, 10.0).n == 5
        t.close()
    server, t = _backend("tcp", TrackerFaults(reply_delay_s=0.6), timeout=0.3, reconnects=1)
    with server:
        with pytest.raises(DeviceError, match="no answer"):
            t.connect()
        t.close()


@pytest.mark.timeout(30)
def test_dropped_connection_reconnects_and_loses_no_point():
    server, t = _backend("tcp", TrackerFaults(drop_after_lines=12))
    with server:
        t.connect()
        s = t.measure(20, 10.0)
        assert s.n == 20 and t.reconnections >= 1 and server.connections >= 2
        np.testing.assert_allclose(s.mean, TRUTH, atol=5 * NOISE)
        t.close()


@pytest.mark.timeout(30)
def test_unplugged_serial_device_ends_in_one_clear_error():
    server, t = _backend("pty", reconnects=2)
    with server:
        t.connect()
        assert t.measure(3, 10.0).n == 3
    # The mock has gone: the pty no longer exists, like a USB adapter pulled out.
    with pytest.raises(TransportError, match="unreachable after 2 reconnection attempts"):
        t.measure(3, 10.0)
    t.close()


@pytest.mark.timeout(60)
def test_the_twin_gives_each_sample_its_own_noise_whatever_the_faults():
    """The simulated cell's tracker: a series re-taken after a broken beam or a dropped
    link, or measured again whole, has the numbers of a series measured in one go; the
    next pose, or another arrival at the same pose, has others."""

    def series(faults: TrackerFaults) -> list[np.ndarray]:
        config, cell = simulated_cell_of(None, 5)
        name = next(s.name for s in config.sensor if s.kind == "laser-tracker")
        server = TrackerTwin(cell.target(name), faults=faults)
        host, port = server.start_tcp("127.0.0.5", 0)
        t = LineTracker("t", f"socket://{host}:{port}", timeout=2.0, backoff_s=0.01)
        home, out = cell.q, []
        with server:
            t.connect()
            for dq in (0.01, 0.0, 0.01):  # there, home, there again
                cell.set_q(home + dq)
                out.append(t.measure(20, 10.0).xyz)
            t.close()
        return out

    plain = series(TrackerFaults())
    broken = series(TrackerFaults(beam_break_after=7, beam_breaks=2))
    dropped = series(TrackerFaults(drop_after_lines=12))
    for a, b, c in zip(plain, broken, dropped, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    assert not np.array_equal(plain[0] - plain[0].mean(0), plain[2] - plain[2].mean(0))
    # a whole series measured again at the same pose (the engine's re-ask) is the same
    config, cell = simulated_cell_of(None, 5)
    target = cell.target(next(s.name for s in config.sensor if s.kind == "laser-tracker"))
    np.testing.assert_array_equal(target.sample(20), target.sample(20))
    np.testing.assert_array_equal(target.sample(20)[8:], target.sample(12))
