"""Line protocol version 2 (issue 31): the driver asks for it (``PROTO?``, ``PROTO 2``),
fills each sample's covariance and air, and falls back to version 1 for a tracker that
does not announce it; a version 1 client (``protocol = 1``, or none of this) sees exactly
the version 1 conversation. Against a scripted wire, and against the twin over TCP on
127.0.0.35 (its lines read with a raw socket where the wire itself is the point)."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from cellcal.commands.mock import simulated_cell_of
from cellcal.config import CellConfig
from cellcal.drivers.base import DeviceContext
from cellcal.drivers.tracker import Environment, LineTracker, LineTrackerOptions
from cellcal.drivers.tracker_protocol import Garbage, Point, TrackerError, parse_line
from cellcal.drivers.tracker_versions import covariance
from cellcal.mocks.tracker.emscon_server import noise_covariance
from cellcal.mocks.tracker.server import COVARIANCE, TrackerFaults, TrackerTwin, serve
from tests.drivers.scripted import ScriptedTransport

HOST = "127.0.0.35"
IDN = ("*IDN?", ["OK Acme,AT-B,SN-7,3.1"])
V2 = [IDN, ("PROTO?", ["OK 1,2"]), ("PROTO 2", ["OK 2"]), ("INIT", ["OK"])]
COV = "0.0001 1e-06 -2e-06 0.00012 0 9e-05"
AIR = "21.50 1001.00 40.0"


def _scripted(pairs, protocol=None, **kw):
    t = ScriptedTransport(pairs, drop_at=kw.pop("drop_at", None))
    lt = LineTracker(
        "t", "scripted://", transport=t, timeout=0.2, backoff_s=0.0, protocol=protocol, **kw
    )
    lt.connect()
    return lt, t


def _pt(i: int, t: float, x: float, v2: bool = True) -> str:
    return f"PT {i} {t} {x} 2.0 3.0" + (f" {COV} {AIR}" if v2 else "")


# ---------------------------------------------------------------- the wire


def test_parse_line_reads_both_forms_of_a_point():
    v1 = parse_line(b"PT 2 12.3 -1.5e2 .5 7")
    assert v1 == Point(2, 12.3, -150.0, 0.5, 7.0) and v1.version == 1
    v2 = parse_line(f"PT 2 12.3 -1.5e2 .5 7 {COV} {AIR}".encode())
    assert isinstance(v2, Point) and v2.version == 2
    assert v2.cov == (1e-4, 1e-6, -2e-6, 1.2e-4, 0.0, 9e-5) and v2.air == (21.5, 1001.0, 40.0)
    c = covariance(v2.cov)
    np.testing.assert_array_equal(c, c.T)
    assert c[0, 2] == c[2, 0] == -2e-6 and c[2, 2] == 9e-5
    for bad in (
        f"PT 2 12.3 1 2 3 {COV}",  # no air
        f"PT 2 12.3 1 2 3 {COV} 21.5 1001.0",  # two of three air values
        f"PT 2 12.3 1 2 3 {COV} {AIR} 7",  # one too many
        "PT 2 12.3 1 2 3 nan 0 0 1 0 1 20 1000 40",
        f"PT 2 12.3 1 2 3  {COV} {AIR}",  # two spaces
        f"PT 2 12.3 1 2 3 {COV} 21.5 1001.0 4O",
    ):
        assert isinstance(parse_line(bad.encode()), Garbage), bad


@pytest.mark.timeout(10)
def test_a_long_wrong_point_line_is_garbage_at_once():
    """13 numbers in a regular expression would backtrack for ever on these."""
    for k in (12, 17):
        assert isinstance(parse_line(b"PT 1" + (b" " + b"9" * k) * 13 + b" x"), Garbage)
        assert isinstance(parse_line(b"PT 1" + (b" " + b"9" * k) * 14), Garbage)


def test_the_driver_asks_for_version_2_and_fills_covariance_and_air():
    meas = ("MEAS 2 10", ["OK 2", _pt(0, 1.0, 10.0), "EVT TEMP 21.5", _pt(1, 1.1, 11.0), "END 2"])
    lt, t = _scripted([*V2, meas])
    assert lt.version == 2
    s = lt.measure(2, 10.0)
    assert t.done and t.written == ["*IDN?", "PROTO?", "PROTO 2", "INIT", "MEAS 2 10"]
    assert s.cov is not None and s.cov.shape == (2, 3, 3) and s.meteo is not None
    np.testing.assert_array_equal(s.cov[1], covariance((1e-4, 1e-6, -2e-6, 1.2e-4, 0.0, 9e-5)))
    np.testing.assert_array_equal(s.meteo, [[21.5, 1001.0, 40.0]] * 2)
    np.testing.assert_allclose(s.mean_covariance, s.cov[0] / 2)


@pytest.mark.parametrize("answer", ["ERR 4 UNKNOWN_COMMAND", "ERR 2 NOT_IMPLEMENTED", "OK 1"])
def test_a_tracker_without_version_2_is_spoken_to_in_version_1(answer):
    meas = ("MEAS 1 10", ["OK 1", _pt(0, 1.0, 10.0, v2=False), "END 1"])
    lt, t = _scripted([IDN, ("PROTO?", [answer]), ("INIT", ["OK"]), meas])
    assert lt.version == 1
    s = lt.measure(1, 10.0)
    assert s.n == 1 and s.cov is None and s.meteo is None and t.done


def test_protocol_1_asks_nothing_of_versions():
    lt, t = _scripted([IDN, ("INIT", ["OK"])], protocol=1)
    assert lt.version == 1 and t.written == ["*IDN?", "INIT"]


@pytest.mark.parametrize(
    ("answer", "says"),
    [
        ("ERR 4 UNKNOWN_COMMAND", "speaks line protocol version 1 ('PROTO?' answered ERR 4)"),
        ("OK 1", "speaks line protocol version 1 ('PROTO?' answered OK 1)"),
        ("OK two", "'PROTO?' answered 'OK two': not a list of versions"),
    ],
)
def test_protocol_2_from_a_tracker_without_it_is_one_line(answer, says):
    t = ScriptedTransport([IDN, ("PROTO?", [answer])])
    lt = LineTracker("t", "scripted://", transport=t, timeout=0.2, protocol=2)
    with pytest.raises(TrackerError) as info:
        lt.connect()
    text = str(info.value)
    assert "\n" not in text and says in text and text.startswith("tracker t at scripted://")
    assert info.value.device == "t"


def test_points_of_the_other_version_are_never_data():
    """A v1 line in version 2 (or the reverse) is garbage: counted, the point taken again."""
    meas = ("MEAS 2 10", ["OK 2", _pt(0, 1.0, 10.0), _pt(1, 1.1, 11.0, v2=False), "END 2"])
    again = ("MEAS 1 10", ["OK 1", _pt(0, 2.0, 12.0), "END 1"])
    lt, t = _scripted([*V2, meas, again])
    s = lt.measure(2, 10.0)
    assert t.done and lt.garbage == 1 and s.n == 2 and s.cov is not None
    np.testing.assert_array_equal(s.xyz[:, 0], [10.0, 12.0])
    meas = ("MEAS 1 10", ["OK 1", _pt(0, 1.0, 10.0), "END 1"])
    again = ("MEAS 1 10", ["OK 1", _pt(0, 2.0, 12.0, v2=False), "END 1"])
    lt, t = _scripted([IDN, ("INIT", ["OK"]), meas, again], protocol=1)
    s = lt.measure(1, 10.0)
    assert t.done and lt.garbage == 1 and s.cov is None and s.xyz[0, 0] == 12.0


def test_a_reconnection_asks_for_version_2_again():
    meas = ("MEAS 2 10", ["OK 2", _pt(0, 1.0, 10.0), _pt(1, 1.1, 11.0), "END 2"])
    lt, t = _scripted([*V2, *V2, meas], drop_at=5)
    s = lt.measure(2, 10.0)
    assert lt.reconnections == 1 and t.written.count("PROTO 2") == 2 and s.cov is not None


def test_the_configuration_key():
    base = {"name": "t", "kind": "laser-tracker", "address": "socket://127.0.0.35:1"}
    assert LineTrackerOptions.model_validate(base).protocol is None
    assert LineTrackerOptions.model_validate({**base, "protocol": 2}).protocol == 2
    with pytest.raises(ValueError, match="protocol"):
        LineTrackerOptions.model_validate({**base, "protocol": 3})
    tracker = LineTracker.from_options(
        LineTrackerOptions.model_validate({**base, "protocol": 1}), DeviceContext()
    )
    assert tracker.protocol == 1


# ---------------------------------------------------------------- the twin


class Still:
    def sample(self, n: int) -> np.ndarray:
        return np.tile([1000.0, 200.0, 300.0], (n, 1))


class Raw:
    """A raw TCP client: one request, the lines that answer it."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, timeout=5.0)
        self.buf = b""

    def lines(self, k: int) -> list[str]:
        while self.buf.count(b"\n") < k:
            data = self.sock.recv(65536)
            assert data, "the twin closed the connection"
            self.buf += data
        *out, self.buf = self.buf.split(b"\n", k)
        return [line.decode() for line in out]

    def ask(self, request: str, k: int = 1) -> list[str]:
        self.sock.sendall(request.encode() + b"\n")
        return self.lines(k)

    def close(self) -> None:
        self.sock.close()


@pytest.mark.twin
@pytest.mark.timeout(30)
def test_the_twin_speaks_version_1_until_asked_and_version_2_after():
    with TrackerTwin(Still(), time_scale=1.0) as twin:
        address = twin.start_tcp(HOST, 0)  # returns once listening
        client = Raw(address)
        try:
            assert client.ask("INIT") == ["OK"]
            assert client.ask("PROTO?") == ["OK 1,2"]
            pt = "PT 0 12.100 1000.0000 200.0000 300.0000"
            assert client.ask("MEAS 1 10", 3) == ["OK 1", pt, "END 1"]
            assert client.ask("PROTO 3") == ["ERR 3 BAD_PARAMETER"]
            assert client.ask("PROTO") == ["ERR 3 BAD_PARAMETER"]
            assert client.ask("PROTO? 2") == ["ERR 3 BAD_PARAMETER"]
            assert client.ask("PROTO 2") == ["OK 2"]
            assert client.ask("ENV T=21.5 P=1001 RH=40") == ["OK"]
            pt = "PT 0 12.200 1000.0000 200.0000 300.0000 0.0001 0 0 0.0001 0 0.0001"
            assert client.ask("MEAS 1 10", 3) == ["OK 1", f"{pt} 21.50 1001.00 40.0", "END 1"]
            # PROTO while its series runs is refused (a point every 100 s: it runs)
            assert client.ask("MEAS 10000 0.01") == ["OK 10000"]
            first, busy = client.ask("PROTO 1", 2)
            assert first.startswith("PT 0 ") and len(first.split()) == 15
            assert busy == "ERR 1 BUSY"
            assert client.ask("STOP", 2) == ["OK", "END 1"]
            # a new connection starts in version 1, whatever another one asked for
            other = Raw(address)
            try:
                assert len(other.ask("MEAS 1 10", 3)[1].split()) == 6
            finally:
                other.close()
            assert client.ask("PROTO 1") == ["OK 1"]
            assert len(client.ask("MEAS 1 10", 3)[1].split()) == 6
        finally:
            client.close()


@pytest.mark.twin
@pytest.mark.timeout(30)
def test_a_twin_of_version_1_alone_knows_no_proto_and_the_driver_falls_back():
    with TrackerTwin(Still(), versions=(1,)) as twin:
        host, port = twin.start_tcp(HOST, 0)
        client = Raw((host, port))
        try:
            assert client.ask("PROTO?") == ["ERR 4 UNKNOWN_COMMAND"]
            assert client.ask("PROTO 2") == ["ERR 4 UNKNOWN_COMMAND"]
        finally:
            client.close()
        t = LineTracker("t", f"socket://{host}:{port}", timeout=2.0, protocol=None)
        t.connect()
        try:
            s = t.measure(3, 10.0)
        finally:
            t.close()
        assert t.version == 1 and s.cov is None and s.meteo is None
    with pytest.raises(ValueError, match="versions"):
        TrackerTwin(Still(), versions=(2,))


@pytest.mark.twin
@pytest.mark.timeout(60)
def test_the_simulated_cells_twin_reports_its_noise_covariance_and_air():
    """The mock-mode twin (``serve``): the configured driver asks for version 2 by itself;
    each sample's covariance is the simulated noise's where the target is, its air the
    environment the twin holds; a dropped link is asked for version 2 again."""
    config, cell = simulated_cell_of(None, 5)
    assert isinstance(config, CellConfig)
    options = next(s for s in config.sensor if s.kind == "laser-tracker")
    running = serve(options, cell, 0.0)
    try:
        t = LineTracker.from_options(running.options, DeviceContext())
        t.connect()
        try:
            t.set_environment(Environment(22.0, 990.0, 35.0))
            s = t.measure(20, 10.0)
        finally:
            t.close()
    finally:
        running.server.stop()
    assert t.version == 2 and s.cov is not None and s.meteo is not None
    expected = noise_covariance(cell, options.name)
    np.testing.assert_allclose(s.cov, np.broadcast_to(expected, (20, 3, 3)), rtol=1e-5)
    np.testing.assert_array_equal(s.meteo, [[22.0, 990.0, 35.0]] * 20)
    # the noise the twin drew has that covariance's size (20 samples: loosely)
    assert 0.3 < np.trace(np.cov(s.xyz, rowvar=False)) / np.trace(expected) < 3.0
    # a link that drops is asked for version 2 again, and the series keeps it
    with TrackerTwin(cell.target(options.name), faults=TrackerFaults(drop_after_lines=12)) as tw:
        host, port = tw.start_tcp(HOST, 0)
        t = LineTracker("t", f"socket://{host}:{port}", timeout=2.0, backoff_s=0.01, protocol=2)
        t.connect()
        s = t.measure(20, 10.0)
        t.close()
        assert t.reconnections >= 1 and s.n == 20 and s.cov is not None
        assert tw.requests.count("PROTO 2") == tw.connections
    with TrackerTwin(Still()) as tw:
        host, port = tw.start_tcp(HOST, 0)
        t = LineTracker("t", f"socket://{host}:{port}", timeout=2.0, protocol=2)
        t.connect()
        s = t.measure(2, 10.0)
        t.close()
    assert s.cov is not None
    np.testing.assert_allclose(s.cov[0], COVARIANCE)


@pytest.mark.twin
@pytest.mark.timeout(30)
def test_a_covariance_the_twin_cannot_give_is_no_tracker_and_leaves_it_free():
    with TrackerTwin(Still(), covariance=lambda: np.full((3, 3), np.nan)) as twin:
        client = Raw(twin.start_tcp(HOST, 0))
        try:
            assert client.ask("INIT") == ["OK"]
            assert client.ask("PROTO 2") == ["OK 2"]
            assert client.ask("MEAS 2 10") == ["ERR 38 NO_TRACKER target source failed"]
            assert client.ask("STAT?") == ["OK ready=1 beam=1 meteo=1 init=1"]
            assert client.ask("PROTO 1") == ["OK 1"]
            assert client.ask("MEAS 1 10", 3)[2] == "END 1"
        finally:
            client.close()
