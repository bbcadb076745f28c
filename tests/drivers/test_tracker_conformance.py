"""The conformance check (``cellcal tracker --conformance``, issue 31): every check holds
against the twin, of versions 1 and 2, over TCP and a pty; and a small bridge written
here from the protocol's text, broken one way at a time, fails exactly the check that
names what it got wrong. Over TCP on 127.0.0.36-.39 (the servers listen before they
return)."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from cellcal.drivers.tracker import LineTracker
from cellcal.drivers.tracker_conformance import Conformance, check_conformance
from cellcal.drivers.tracker_protocol import TrackerTimeoutError
from cellcal.drivers.transport import TransportError
from cellcal.mocks.tracker.server import TrackerTwin

pytestmark = [pytest.mark.twin, pytest.mark.slow]

V1_CHECKS = [
    "identification",
    "versions",
    "INIT",
    "STAT?",
    "ENV?",
    "ENV",
    "ENV out of range",
    "SMR",
    "MEAS",
    "MEAS while busy",
    "STOP",
    "unknown command",
    "malformed argument",
    "line too long",
]
V2_CHECKS = ["PROTO 2", "MEAS in version 2", "PROTO of a version not announced", "PROTO 1"]
FRESH = "new connection in version 1"


class Still:
    def sample(self, n: int) -> np.ndarray:
        return np.tile([1000.0, 200.0, 300.0], (n, 1)) + np.arange(n)[:, None] * 1e-4


def _summary(result: Conformance) -> str:
    return "; ".join(f"{c.name}: expected {c.expected}, got {c.got}" for c in result.checks)


# ---------------------------------------------------------------- the twin


@pytest.mark.timeout(60)
@pytest.mark.parametrize("versions", [(1, 2), (1,)])
def test_every_check_holds_against_the_twin_over_tcp(versions):
    with TrackerTwin(Still(), time_scale=0.01, versions=versions) as twin:
        host, port = twin.start_tcp("127.0.0.36", 0)  # returns once listening
        result = check_conformance(f"socket://{host}:{port}", timeout=2.0)
        assert result.passed, _summary(result)
        assert result.idn == "cellcal,mock-tracker,SIM-0001,1.0" and result.versions == versions
        names = [c.name for c in result.checks]
        assert names == (V1_CHECKS + V2_CHECKS + [FRESH] if 2 in versions else V1_CHECKS)
        # it leaves the tracker as it found it: the air, the reflector, no series running
        assert twin._environment() == (20.0, 1013.25, 45.0) and twin._reflector() == "RRR15"
        assert not twin._busy()


@pytest.mark.timeout(60)
def test_every_check_holds_against_the_twin_over_a_pty():
    """A serial line has no new connection to check."""
    with TrackerTwin(Still(), time_scale=0.01) as twin:
        result = check_conformance(twin.start_pty(), timeout=2.0)
    assert result.passed, _summary(result)
    assert [c.name for c in result.checks] == V1_CHECKS + V2_CHECKS


@pytest.mark.timeout(60)
def test_a_twin_that_talks_garbage_fails_where_it_did():
    from cellcal.mocks.tracker.server import TrackerFaults

    with TrackerTwin(Still(), time_scale=0.01, faults=TrackerFaults(garbage_every=4)) as twin:
        host, port = twin.start_tcp("127.0.0.36", 0)
        result = check_conformance(f"socket://{host}:{port}", timeout=2.0)
    assert not result.passed
    for check in result.checks:
        if not check.ok:
            assert check.expected == "only lines of the protocol", _summary(result)


@pytest.mark.timeout(30)
def test_nothing_listening_or_nothing_answering_is_one_line():
    with pytest.raises(TransportError) as info:
        check_conformance("socket://127.0.0.37:9", timeout=1.0)
    assert str(info.value).startswith("tracker at socket://127.0.0.37:9: ")
    assert "\n" not in str(info.value)
    with Bridge("127.0.0.37", "mute") as bridge, pytest.raises(TrackerTimeoutError) as info:
        check_conformance(bridge.address, timeout=0.5)
    assert str(info.value) == (
        f"tracker at {bridge.address}: no answer to '*IDN?' within 0.5 s: is it a tracker or "
        "bridge that speaks the line protocol?"
    )


# ---------------------------------------------------------------- a bridge, broken


@pytest.mark.timeout(30)
def test_the_driver_says_a_silent_link_is_open_not_unreachable():
    """The driver on a link that opens but never answers: the handshake is asked once
    more on a link opened again (docs/tracker.md), then one line — a timeout, not
    "unreachable after 5 reconnection attempts" after half a minute."""
    with Bridge("127.0.0.37", "mute") as bridge:
        tracker = LineTracker("t", bridge.address, timeout=0.3, backoff_s=0.01, reconnects=5)
        with pytest.raises(TrackerTimeoutError) as info:
            tracker.connect()
    assert str(info.value) == (
        f"tracker t at {bridge.address}: no answer to '*IDN?' within 0.3 s, twice, with the "
        "link open: is it a tracker or bridge that speaks the line protocol? (`cellcal "
        "tracker --conformance` tells more)"
    )
    assert tracker.reconnections == 1


COV = (1e-4, 2e-6, -1e-6, 1.2e-4, 0.0, 9e-5)


class Bridge:
    """A line-protocol tracker in a hundred lines, from docs/tracker.md alone, with one
    thing broken (``broken``; "" for none). A point every 2 ms, whatever the rate."""

    INTERVAL = 0.002

    def __init__(self, host: str, broken: str = "", versions: tuple[int, ...] = (1, 2)) -> None:
        self.broken, self.versions = broken, versions
        self.env = [20.0, 1013.25, 45.0]
        self.smr = "RRR15"
        self.shared_version = 1  # "sticky": one version for every connection
        self.listener = socket.create_server((host, 0))  # listening when this returns
        self.listener.settimeout(0.05)
        self.address = f"socket://{host}:{self.listener.getsockname()[1]}"
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._accept, daemon=True)]
        self.threads[0].start()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(5.0)
        self.listener.close()

    def _accept(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            t = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            self.threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket) -> None:
        link = Link(version=2 if self.broken == "v2-always" else 1)
        buf = b""
        with conn:
            while not self.stop.is_set():
                ready, _, _ = select.select([conn], [], [], self.INTERVAL)
                if ready:
                    try:
                        data = conn.recv(65536)
                    except OSError:
                        return
                    if not data:
                        return
                    buf += data
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        answer = self._answer(link, line.rstrip(b"\r").decode("latin-1"))
                        if answer is None:
                            return  # closes the link
                        self._send(conn, answer)
                if link.series is not None:
                    self._send(conn, self._point(link))

    @staticmethod
    def _send(conn: socket.socket, lines: list[str]) -> None:
        if lines:
            with contextlib.suppress(OSError):
                conn.sendall("".join(f"{line}\n" for line in lines).encode("latin-1"))

    def _version(self, link: Link) -> int:
        return self.shared_version if self.broken == "v2-sticky" else link.version

    def _point(self, link: Link) -> list[str]:
        assert link.series is not None
        n, i = link.series
        if i == n:
            link.series = None
            return [f"END {n + 1 if self.broken == 'end-count' else n}"]
        link.series = (n, i + 1)
        line = f"PT {i} {1.0 + i * 0.1:.3f} {1000 + i * 1e-4:.4f} 200.0000 300.0000"
        if self._version(link) == 2:
            cov = (-1e-4, *COV[1:]) if self.broken == "v2-not-psd" else COV
            rh = 120.0 if self.broken == "v2-air" else self.env[2]
            line += " " + " ".join(f"{c:g}" for c in cov)
            line += f" {self.env[0]:.2f} {self.env[1]:.2f} {rh:.1f}"
        return [line]

    def _answer(self, link: Link, line: str) -> list[str] | None:
        """The lines that answer ``line`` (None: close the link)."""
        b = self.broken
        if b == "mute":
            return []
        if len(line) > 256:
            return ["ERR 4 UNKNOWN_COMMAND" if b == "no-line-limit" else "ERR 3 BAD_PARAMETER"]
        cmd, *args = line.split() or [""]
        if cmd == "*IDN?":
            return ["OK acme,bridge,7" if b == "idn-fields" else "OK acme,bridge,B-7,0.9"]
        if cmd == "PROTO?" and 2 in self.versions:
            return ["OK two" if b == "proto-garbled" else "OK 1,2"]
        if cmd == "PROTO" and 2 in self.versions:
            if link.series is not None:
                return ["ERR 1 BUSY"]
            if args not in (["1"], ["2"]) and b != "proto-any":
                return ["ERR 3 BAD_PARAMETER"]
            if b != "v2-always":
                link.version = self.shared_version = int(args[0])
            return [f"OK {args[0]}"]
        if cmd == "INIT":
            return ["ERR 38 NO_TRACKER"] if b == "init-fails" else ["OK"]
        if cmd == "STAT?":
            garbage = ["\x00\xffnoise"] if b == "garbage" else []
            stat = "OK ready=1 beam=1" if b == "stat-short" else "OK ready=1 beam=1 meteo=1 init=1"
            return [*garbage, stat]
        if cmd == "ENV?":
            return ["OK T={} P={} RH={}".format(*self.env)]
        if cmd == "ENV":
            try:
                f = dict(a.split("=", 1) for a in args)
                env = [float(f["T"]), float(f["P"]), float(f["RH"])]
            except (ValueError, KeyError):
                return ["ERR 3 BAD_PARAMETER"]
            in_range = 0 <= env[0] <= 40 and 600 <= env[1] <= 1100 and 0 <= env[2] <= 95
            if not in_range and b != "env-no-range":
                return ["ERR 57 METEO_OUT_OF_RANGE"]
            self.env = [env[0] + 1.0, *env[1:]] if b == "env-not-kept" else env
            return ["OK"]
        if cmd == "SMR?":
            return ["OK rrr15" if b == "smr-lower" else f"OK {self.smr}"]
        if cmd == "SMR":
            if args[:1] not in (["RRR15"], ["RRR05"], ["RRR0875"], ["TBR05"]):
                return ["OK"] if b == "malformed-accepted" else ["ERR 3 BAD_PARAMETER"]
            self.smr = args[0]
            return ["OK"]
        if cmd == "MEAS":
            if link.series is not None and b != "busy-restarts":
                return ["ERR 1 BUSY"]
            if not args or not args[0].isdigit():
                return ["ERR 3 BAD_PARAMETER"]
            link.series = (int(args[0]), 0)
            return [f"OK {args[0]}"]
        if cmd == "STOP":
            if link.series is None:
                return ["OK"]
            k, link.series = link.series[1], None
            return ["OK"] if b == "stop-no-end" else ["OK", f"END {k}"]
        if b == "closes":
            return None
        if b == "silent-unknown":
            return []
        return ["ERR 3 BAD_PARAMETER"] if b == "unknown-as-3" else ["ERR 4 UNKNOWN_COMMAND"]


@dataclass
class Link:
    """One connection's state: its version, its series (n, points sent)."""

    version: int = 1
    series: tuple[int, int] | None = None


@pytest.fixture
def bridge() -> Iterator:
    started: list[Bridge] = []

    def start(broken: str, host: str = "127.0.0.38", **kw: object) -> Bridge:
        started.append(Bridge(host, broken, **kw))  # type: ignore[arg-type]
        return started[-1]

    yield start
    for b in started:
        b.__exit__()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("versions", [(1, 2), (1,)])
def test_the_bridge_unbroken_passes(bridge, versions):
    result = check_conformance(bridge("", versions=versions).address, timeout=1.0)
    assert result.passed, _summary(result)
    assert len(result.checks) == (len(V1_CHECKS + V2_CHECKS) + 1 if 2 in versions else 14)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("broken", "failing", "says"),
    [
        ("idn-fields", {"identification"}, "got OK acme,bridge,7"),
        ("proto-garbled", {"versions"}, "got OK two"),
        ("init-fails", {"INIT"}, "got ERR 38 NO_TRACKER"),
        ("stat-short", {"STAT?"}, "got OK ready=1 beam=1"),
        ("garbage", {"STAT?"}, "only lines of the protocol"),
        ("env-not-kept", {"ENV"}, "ENV? to answer T=20.00 P=1013.25 RH=45.0"),
        ("env-no-range", {"ENV out of range"}, "ERR 57 METEO_OUT_OF_RANGE"),
        ("smr-lower", {"SMR"}, "got OK rrr15"),
        ("end-count", {"MEAS", "MEAS in version 2", "PROTO 1", FRESH}, "got END 6"),
        ("busy-restarts", {"MEAS while busy"}, "ERR 1 BUSY to 'MEAS 1 10'"),
        ("stop-no-end", {"STOP"}, "END <k> after OK to 'STOP'"),
        ("unknown-as-3", {"unknown command"}, "got ERR 3 BAD_PARAMETER"),
        ("silent-unknown", {"unknown command"}, "got no answer within 1 s"),
        ("malformed-accepted", {"malformed argument"}, "ERR 3 BAD_PARAMETER to 'SMR RRR99'"),
        ("no-line-limit", {"line too long"}, "got ERR 4 UNKNOWN_COMMAND"),
        ("v2-not-psd", {"MEAS in version 2"}, "a positive semi-definite covariance"),
        ("v2-air", {"MEAS in version 2"}, "RH 120.0"),
        ("proto-any", {"PROTO of a version not announced"}, "got OK 3"),
        ("v2-sticky", {FRESH}, "PT 0 in version 1's form"),
        (
            "v2-always",
            {"MEAS", "MEAS while busy", "STOP", "PROTO 1", FRESH},
            "PT 0 in version 1's form",
        ),
    ],
)
def test_each_broken_bridge_fails_the_check_that_names_it(bridge, broken, failing, says):
    result = check_conformance(bridge(broken).address, timeout=1.0)
    assert set(result.failed) == failing, _summary(result)
    first = next(c for c in result.checks if not c.ok)
    assert says in f"expected {first.expected}, got {first.got}", _summary(result)
    # every check ran (those of version 2 when it was announced)
    assert len(result.checks) == (19 if 2 in result.versions else 14), _summary(result)


@pytest.mark.timeout(30)
def test_a_bridge_that_closes_the_link_fails_that_check_and_the_rest_go_on(bridge):
    result = check_conformance(bridge("closes", host="127.0.0.39").address, timeout=1.0)
    assert result.failed == ("unknown command",), _summary(result)
    check = next(c for c in result.checks if not c.ok)
    assert check.expected == "the link to stay up" and check.got.startswith("it failed (")
