"""The emScon driver against the emScon twin over real sockets (127.0.0.240–.249): the
handshake, measurements with their covariance and air, and every fault a campaign meets
— a broken beam (waited for, or searched), a warm-up, a second client, a dropped link,
air out of range, units the tracker does not take, bytes that are not the protocol."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from cellcal.drivers import emscon_packets as p
from cellcal.drivers.emscon import EmsconOptions, EmsconTracker
from cellcal.errors import DeviceError
from cellcal.mocks.tracker import emscon_state
from cellcal.mocks.tracker.emscon_server import EmsconTwin
from cellcal.mocks.tracker.emscon_state import EmsconFaults, EmsconState

pytestmark = pytest.mark.timeout(60)

TRUE = np.array([2500.0, -300.0, 450.0])
SIGMA = np.array([[4e-4, 1e-4, 0.0], [1e-4, 2.5e-4, -5e-5], [0.0, -5e-5, 1e-4]])


@contextmanager
def twin(host: str, **kwargs: object) -> Iterator[EmsconTwin]:
    rng = np.random.default_rng(7)
    chol = np.linalg.cholesky(SIGMA)
    state = EmsconState(
        sample=lambda: TRUE + chol @ rng.normal(size=3),
        covariance=lambda: SIGMA,
        started=time.monotonic(),
        time_scale=0.001,
        **kwargs,  # type: ignore[arg-type]
    )
    server = EmsconTwin(state)
    server.start_tcp(host, 0)
    try:
        yield server
    finally:
        server.stop()


def tracker(server: EmsconTwin, **options: object) -> EmsconTracker:
    assert server.address is not None
    host, port = server.address
    return EmsconTracker(EmsconOptions(name="tracker", address=f"{host}:{port}", **options))


def test_handshake_and_measurements_with_covariance_and_air():
    with twin("127.0.0.240") as server:
        t = tracker(server, reflector="RRR 0.5in", measure_time_ms=500)
        t.connect()
        try:
            d = t.describe()
            assert (d.family, d.maker, d.model, d.serial) == (
                "laser-tracker/emscon", "Leica", "AT401", str(emscon_state.SERIAL),
            )  # fmt: skip
            assert d.firmware == "3.6.1254"
            s = t.measure(8, 10.0)
        finally:
            t.close()
        sent = server.commands
    assert s.n == 8 and s.retries == 0 and s.note == ""
    assert np.abs(s.xyz - TRUE).max() < 0.1
    assert s.cov is not None and np.allclose(s.cov, SIGMA)  # type 9: the full covariance
    assert s.meteo is not None and np.allclose(s.meteo, [20.0, 1013.25, 45.0])
    # what cellcal asked for, in order, before measuring
    start = sent.index(p.START_MEASUREMENT)
    for c in (p.SET_UNITS, p.GET_UNITS, p.SET_SYSTEM_SETTINGS, p.INITIALIZE,
              p.SET_STATIONARY_MODE_PARAMS, p.SET_STATISTIC_MODE, p.SET_REFLECTOR):  # fmt: skip
        assert c in sent[:start], p.LAYOUTS[c].name
    assert server.state.settings.measure_ms == 500 and server.state.settings.reflector == 8
    assert server.state.settings.statistic[0] == p.STATISTIC_EXTENDED


@pytest.mark.parametrize(
    ("relock", "search"),
    [("wait", None), ("find-reflector", p.FIND_REFLECTOR), ("bird-bath", p.GO_BIRD_BATH)],
)
def test_a_broken_beam_is_relocked_and_the_measurement_taken_again(relock, search):
    faults = EmsconFaults(beam_break_every=3, beam_restore_s=0.05)
    with twin("127.0.0.241", faults=faults) as server:
        t = tracker(server, relock=relock)
        t.connect()
        try:
            s = t.measure(6, 10.0)
        finally:
            t.close()
    assert s.n == 6 and s.retries == 2
    assert "no stationary result" in s.note and "8 attempts" in s.note
    if search is not None:
        assert server.commands.count(search) == 2


def test_a_beam_that_does_not_come_back_ends_the_series_with_what_it_has():
    faults = EmsconFaults(beam_break_every=3, beam_restore_s=30.0)
    with twin("127.0.0.242", faults=faults) as server:
        t = tracker(server, beam_wait_s=0.2)
        t.connect()
        try:
            s = t.measure(5, 10.0)
        finally:
            t.close()
    assert s.n == 2 and "no reflector found 0.2 s after the beam broke" in s.note


def test_warm_up_is_waited_for_or_named():
    with twin("127.0.0.243", faults=EmsconFaults(warmup_s=0.5)) as server:
        t = tracker(server)
        t.connect()  # waits for the laser (polled), then initialises
        t.close()
        assert server.state.initialized
    with twin("127.0.0.243", faults=EmsconFaults(warmup_s=60.0)) as server:
        t = tracker(server, warmup_timeout_s=0.0)
        with pytest.raises(DeviceError, match="not warmed up after 0 s") as err:
            t.connect()
        assert err.value.device == "tracker" and "\n" not in str(err.value)


def test_a_second_client_is_named():
    with twin("127.0.0.244") as server:
        first = tracker(server)
        first.connect()
        try:
            with pytest.raises(DeviceError, match="another client is connected") as err:
                tracker(server).connect()
            assert "127.0.0.244" in str(err.value)
            assert first.measure(1, 1.0).n == 1  # the first goes on
        finally:
            first.close()
        assert server.refused == 1


def test_a_dropped_link_is_one_line():
    with twin("127.0.0.245") as server:
        t = tracker(server)
        t.connect()
        server.stop()
        with pytest.raises(DeviceError, match=r"closed the connection|connection lost") as err:
            t.measure(3, 1.0)
        assert "\n" not in str(err.value)
        t.close()


def test_air_out_of_range_and_units_not_taken(monkeypatch):
    monkeypatch.setattr(emscon_state, "T_RANGE", (0.0, 40.0))
    with twin("127.0.0.246", meteo_station=False) as server:
        t = tracker(
            server, meteo="manual", temperature_c=45.0, pressure_hpa=1000.0, humidity_pct=40.0
        )
        with pytest.raises(DeviceError, match=r"refuses the configured air \(45.0 °C"):
            t.connect()
    with twin("127.0.0.246", meteo_station=False) as server:
        t = tracker(server)
        with pytest.raises(DeviceError, match='no meteo station: set meteo = "manual"'):
            t.connect()
    monkeypatch.setattr(EmsconState, "_set", _units_ignored)
    with twin("127.0.0.246") as server, pytest.raises(DeviceError, match="reports units"):
        tracker(server).connect()


def _units_ignored(self: EmsconState, command: int, args: tuple, now: float) -> list[bytes]:
    return [self._reply(command, p.OK)]  # "OK", and nothing set


def test_manual_air_is_sent_and_comes_back_with_each_result():
    with twin("127.0.0.247", meteo_station=False) as server:
        t = tracker(
            server, meteo="manual", temperature_c=23.5, pressure_hpa=990.0, humidity_pct=38.0
        )
        t.connect()
        try:
            s = t.measure(2, 1.0)
        finally:
            t.close()
    assert s.meteo is not None and np.allclose(s.meteo, [[23.5, 990.0, 38.0]] * 2)


def test_bytes_that_are_not_the_protocol_close_the_link_in_one_line():
    listener = socket.create_server(("127.0.0.248", 0))
    host, port = listener.getsockname()

    def speak_http() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.recv(64)
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")
            time.sleep(0.5)

    thread = threading.Thread(target=speak_http, daemon=True)
    thread.start()
    t = EmsconTracker(EmsconOptions(name="t1", address=f"{host}:{port}", timeout_s=5))
    with pytest.raises(DeviceError, match="not the emScon protocol") as err:
        t.connect()
    assert "tracker t1 at 127.0.0.248" in str(err.value) and "\n" not in str(err.value)
    thread.join(5)
    listener.close()


def test_configuration_refusals():
    with pytest.raises(ValueError, match="needs temperature_c, pressure_hpa and humidity_pct"):
        EmsconOptions(name="t", address="10.0.0.5", meteo="manual", temperature_c=20.0)
    with pytest.raises(ValueError, match="are for meteo"):
        EmsconOptions(name="t", address="10.0.0.5", temperature_c=20.0)
    with pytest.raises(ValueError, match="relock"):
        EmsconOptions(name="t", address="10.0.0.5", relock="shout")  # type: ignore[arg-type]
