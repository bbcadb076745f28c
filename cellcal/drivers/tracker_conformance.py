"""The conformance check of a tracker or bridge that speaks the tracker line protocol
(``cellcal tracker --address ADDR --conformance``, ``docs/tracker.md``): every request
and fault a campaign relies on, one check each, and what the tracker got wrong.

Pure client code over the driver's layers (transport → line framing → ``parse_line``),
on one connection: identification, the versions announced, ``INIT``, ``STAT?``,
``ENV?``, ``ENV`` (set to the values read: the tracker is left as it was) and ``ENV``
out of range, ``SMR``, ``MEAS n rate`` (its n points and ``END``), ``MEAS`` while a
series runs, ``STOP`` in the middle of one, an unknown command, malformed arguments, a
line over 256 bytes, and when the tracker announces version 2: ``PROTO 2``, a series
with covariances (symmetric, positive semi-definite) and air (in the ranges of ``ENV``),
a version it does not speak refused, ``PROTO 1``, and over TCP a new connection that
starts in version 1. A check that fails says what the protocol expects and what came;
the lines of the protocol that are not events must be the only ones the tracker sends.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cellcal.drivers.base import label
from cellcal.drivers.tracker_probe import Probe, is_err, text_of
from cellcal.drivers.tracker_protocol import (
    ERROR_TEXT,
    End,
    Message,
    Ok,
    Point,
    TrackerTimeoutError,
    parse_versions,
)
from cellcal.drivers.tracker_versions import covariance
from cellcal.drivers.transport import SerialUrlTransport, Transport, TransportError

REFLECTORS = ("RRR15", "RRR05", "RRR0875", "TBR05")
RANGES = {"T": (0.0, 40.0), "P": (600.0, 1100.0), "RH": (0.0, 95.0)}
#: the series that ``MEAS`` while busy and ``STOP`` interrupt: the longest there is
LONG = 10000
#: points of the series measured whole
SHORT = 5


@dataclass(frozen=True)
class Check:
    """One check: ``ok``, and what the protocol expects and what the tracker did."""

    name: str
    ok: bool
    expected: str
    got: str


@dataclass(frozen=True)
class Conformance:
    """Every check run against the tracker at ``address``; ``versions``: those it
    announced (``PROTO?``), ``idn``: its ``*IDN?`` answer."""

    address: str
    idn: str
    versions: tuple[int, ...]
    checks: tuple[Check, ...]

    @property
    def passed(self) -> bool:
        return all(c.ok for c in self.checks)

    @property
    def failed(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.checks if not c.ok)


class _WrongError(Exception):
    """A check failed: what the protocol expects, what came."""

    def __init__(self, expected: str, got: str) -> None:
        super().__init__(f"expected {expected}, got {got}")
        self.expected, self.got = expected, got


class ConformanceCheck:
    """The checks, run in order on one connection (:meth:`run`)."""

    def __init__(
        self,
        address: str,
        *,
        timeout: float = 5.0,
        rate_hz: float = 10.0,
        init_timeout: float = 60.0,
        transport: Transport | None = None,
    ) -> None:
        self.address = address
        self.where = label("tracker", address)
        self.rate = rate_hz
        self.init_timeout = max(timeout, init_timeout)
        self.wire = Probe(transport or SerialUrlTransport(address), timeout)
        self.line_timeout = timeout + 2.0 / rate_hz
        self.idn = ""
        self.versions: tuple[int, ...] = (1,)
        self.env: tuple[float, float, float] | None = None
        self.series: int | None = None  # points received of a long series still running
        self.checks: list[Check] = []

    # ---------------------------------------------------------------- running

    def run(self) -> Conformance:
        """Every check; a tracker that cannot be reached at all is one TransportError."""
        try:
            self.wire.open()
        except TransportError as exc:
            raise TransportError(f"{self.where}: {exc}") from None
        try:
            self._all()
        except TransportError as exc:
            raise TransportError(f"{self.where}: {exc}") from None
        finally:
            self.wire.close()
        return Conformance(self.address, self.idn, self.versions, tuple(self.checks))

    def _all(self) -> None:
        steps: list[tuple[str, Callable[[], str]]] = [
            ("identification", self._identification),
            ("versions", self._versions),
            ("INIT", self._init),
            ("STAT?", self._status),
            ("ENV?", self._env_query),
            ("ENV", self._env_set),
            ("ENV out of range", self._env_out_of_range),
            ("SMR", self._reflector),
            ("MEAS", self._measure),
            ("MEAS while busy", self._busy),
            ("STOP", self._stop),
            ("unknown command", self._unknown),
            ("malformed argument", self._malformed),
            ("line too long", self._too_long),
        ]
        for name, step in steps:
            self.checks.append(self._one(name, step))
            if name == "identification" and self.checks[0].got.startswith("no answer"):
                raise TrackerTimeoutError(
                    f"{self.where}: no answer to '*IDN?' within {self.wire.timeout:g} s: is "
                    "it a tracker or bridge that speaks the line protocol?"
                )
        if 2 not in self.versions:
            return
        steps = [
            ("PROTO 2", lambda: self._proto(2)),
            ("MEAS in version 2", self._measure_2),
            ("PROTO of a version not announced", self._proto_unknown),
            ("PROTO 1", self._proto_1),
        ]
        if self.address.startswith("socket://"):
            steps.append(("new connection in version 1", self._fresh))
        for name, step in steps:
            self.checks.append(self._one(name, step))

    def _one(self, name: str, step: Callable[[], str]) -> Check:
        self.wire.junk.clear()
        try:
            got = step()
        except _WrongError as wrong:
            self._resync()
            return Check(name, False, wrong.expected, wrong.got)
        except TransportError as exc:
            return self._lost(name, exc)
        if self.wire.junk:
            n = len(self.wire.junk)
            return Check(
                name,
                False,
                "only lines of the protocol",
                f"{n} line{'s' * (n > 1)} that {'are' if n > 1 else 'is'} not, the first "
                f"{self.wire.junk[0]!r}",
            )
        return Check(name, True, "", got)

    def _lost(self, name: str, exc: TransportError) -> Check:
        self.series = None
        try:
            self.wire.open()
        except TransportError as again:
            raise TransportError(f"link lost during the check {name!r} ({again})") from None
        return Check(name, False, "the link to stay up", f"it failed ({exc})")

    def _resync(self) -> None:
        """After a check failed: stop a series that may run, drop what still comes."""
        try:
            if self.series is not None:
                self.wire.send("STOP")
            self.series = None
            self.wire.drain()
        except TransportError:
            self.wire.close()
            self.wire.open()

    def _expect(self, request: str | bytes, expected: str, timeout: float | None = None) -> Ok:
        msg = self.wire.ask(request, timeout)
        if not isinstance(msg, Ok):
            raise _WrongError(
                expected, text_of(msg, self.wire.timeout if timeout is None else timeout)
            )
        return msg

    def _refused(self, request: str | bytes, code: int) -> str:
        msg = self.wire.ask(request)
        expected = f"ERR {code} {ERROR_TEXT[code]}"
        if not is_err(msg, code):
            name = request if isinstance(request, str) else f"a line of {len(request)} bytes"
            if isinstance(msg, Ok) and isinstance(request, str) and request.startswith("MEAS"):
                self.series = 0
            raise _WrongError(f"{expected} to {name!r}", text_of(msg, self.wire.timeout))
        return text_of(msg, self.wire.timeout)

    # ---------------------------------------------------------------- requests

    def _identification(self) -> str:
        payload = self._expect("*IDN?", "OK <maker>,<model>,<serial>,<firmware>").payload
        self.idn = payload
        fields = [f.strip() for f in payload.split(",")]
        if len(fields) != 4 or not all(fields):
            raise _WrongError(
                "OK <maker>,<model>,<serial>,<firmware> (four fields)", f"OK {payload}"
            )
        return f"OK {payload}"

    def _versions(self) -> str:
        msg = self.wire.ask("PROTO?")
        if is_err(msg, 4) or is_err(msg, 2):
            return f"{text_of(msg, 0)}: version 1 only"
        versions = parse_versions(msg.payload) if isinstance(msg, Ok) else None
        if versions is None:
            expected = "OK <versions> (OK 1,2) or, from a version 1 tracker, ERR 4 UNKNOWN_COMMAND"
            raise _WrongError(expected, text_of(msg, self.wire.timeout))
        self.versions = versions
        return f"OK {msg.payload.strip()}" if isinstance(msg, Ok) else ""

    def _init(self) -> str:
        self._expect("INIT", "OK", self.init_timeout)
        return "OK"

    def _status(self) -> str:
        expected = "OK ready=<0|1> beam=<0|1> meteo=<0|1> init=1"
        payload = self._expect("STAT?", expected).payload
        f = dict(kv.split("=", 1) for kv in payload.split() if "=" in kv)
        keys = ("ready", "beam", "meteo", "init")
        if any(f.get(k) not in ("0", "1") for k in keys) or f["init"] != "1":
            raise _WrongError(expected, f"OK {payload}")
        if f["beam"] != "1":
            raise _WrongError(
                f"{expected} with beam=1 (the MEAS checks need the beam)", f"OK {payload}"
            )
        return f"OK {payload}"

    def _read_env(self, expected: str) -> tuple[float, float, float]:
        payload = self._expect("ENV?", expected).payload
        f = dict(kv.split("=", 1) for kv in payload.split() if "=" in kv)
        try:
            T, P, RH = (float(f[k]) for k in ("T", "P", "RH"))
        except (KeyError, ValueError):
            raise _WrongError(expected, f"OK {payload}") from None
        return T, P, RH

    def _env_query(self) -> str:
        expected = "OK T=<°C> P=<hPa> RH=<%> within 0–40 °C, 600–1100 hPa, 0–95 %"
        env = self._read_env(expected)
        if not all(lo <= v <= hi for v, (lo, hi) in zip(env, RANGES.values(), strict=True)):
            raise _WrongError(expected, "T={} P={} RH={}".format(*env))
        self.env = env
        return "T={} P={} RH={}".format(*env)

    def _env_set(self) -> str:
        if self.env is None:
            raise _WrongError("OK (to ENV set to what ENV? answered)", "not run: ENV? failed")
        T, P, RH = self.env
        request = f"ENV T={T:.2f} P={P:.2f} RH={RH:.1f}"
        self._expect(request, f"OK to {request!r}")
        back = self._read_env("OK T=<°C> P=<hPa> RH=<%>")
        if not np.allclose(back, (T, P, RH), atol=0.06):
            raise _WrongError(f"ENV? to answer {request[4:]}", "T={} P={} RH={}".format(*back))
        return f"OK to {request!r}"

    def _env_out_of_range(self) -> str:
        if self.env is not None:
            self.env = self._read_env("OK T=<°C> P=<hPa> RH=<%>")
        T, P, RH = self.env or (20.0, 1013.25, 45.0)
        request = f"ENV T=55.00 P={P:.2f} RH={RH:.1f}"
        msg = self.wire.ask(request)
        if not is_err(msg, 57):
            if isinstance(msg, Ok) and self.env is not None:
                self.wire.ask(f"ENV T={T:.2f} P={P:.2f} RH={RH:.1f}")  # as it was
            expected = f"ERR 57 METEO_OUT_OF_RANGE to {request!r}"
            raise _WrongError(expected, text_of(msg, self.wire.timeout))
        if self.env is not None:
            back = self._read_env("OK T=<°C> P=<hPa> RH=<%>")
            if not np.allclose(back, self.env, atol=0.06):
                expected = "the environment unchanged by a refused ENV"
                raise _WrongError(expected, "T={} P={} RH={}".format(*back))
        return text_of(msg, 0)

    def _reflector(self) -> str:
        expected = f"OK <type>, one of {' '.join(REFLECTORS)}"
        kind = self._expect("SMR?", expected).payload.strip()
        if kind not in REFLECTORS:
            raise _WrongError(expected, f"OK {kind}")
        self._expect(f"SMR {kind}", f"OK to 'SMR {kind}'")
        return f"OK {kind}; OK to 'SMR {kind}'"

    # ---------------------------------------------------------------- series

    def _points(self, n: int, version: int) -> tuple[list[Point], End]:
        """A series' points (index 0 on, in ``version``'s form) and its END, within the
        time the driver gives a series."""
        got: list[Point] = []
        budget = self.wire.timeout + 1.5 * n / self.rate + 2.0
        deadline = time.monotonic() + budget
        while (left := deadline - time.monotonic()) > 0:
            msg = self.wire.read(min(self.line_timeout, left))
            if isinstance(msg, Point) and msg.i == len(got) and msg.version == version:
                got.append(msg)
            elif isinstance(msg, End):
                return got, msg
            elif isinstance(msg, Point):
                raise _WrongError(f"PT {len(got)} in version {version}'s form", text_of(msg, 0))
            else:
                expected = f"PT {len(got)} or END {n}"
                raise _WrongError(expected, text_of(msg, min(self.line_timeout, left)))
        raise _WrongError(f"END {n} within {budget:.3g} s", f"{len(got)} points and no END")

    def _series(self, n: int, version: int) -> list[Point]:
        request = f"MEAS {n} {self.rate:g}"
        msg = self._expect(request, f"OK {n} to {request!r}")
        if msg.payload.strip() != str(n):
            raise _WrongError(f"OK {n} to {request!r}", text_of(msg, 0))
        points, end = self._points(n, version)
        if end.count != n:
            raise _WrongError(f"END {n} after {n} points", f"END {end.count} after {len(points)}")
        t = [p.t for p in points]
        if any(b < a for a, b in itertools.pairwise(t)):
            raise _WrongError("t, the tracker's clock, never going back", f"t {t}")
        return points

    def _measure(self) -> str:
        self._series(SHORT, 1)
        return f"OK {SHORT}, PT 0 to PT {SHORT - 1}, END {SHORT}"

    def _start_long(self) -> None:
        request = f"MEAS {LONG} {self.rate:g}"
        msg = self._expect(request, f"OK {LONG} to {request!r}")
        self.series = 0
        if msg.payload.strip() != str(LONG):
            raise _WrongError(f"OK {LONG} to {request!r}", text_of(msg, 0))
        first = self.wire.read(self.line_timeout)
        if not (isinstance(first, Point) and first.i == 0 and first.version == 1):
            raise _WrongError(f"PT 0 after 'OK {LONG}'", text_of(first, self.line_timeout))
        self.series = 1

    def _until_reply(self) -> Message | None:
        """The next line that is not a point of the running series (those counted)."""
        assert self.series is not None
        while True:
            msg = self.wire.read(self.line_timeout)
            if isinstance(msg, Point) and msg.i == self.series and msg.version == 1:
                self.series += 1
                continue
            return msg

    def _busy(self) -> str:
        self._start_long()
        self.wire.send(f"MEAS 1 {self.rate:g}")
        msg = self._until_reply()
        if isinstance(msg, End):
            self.series = None
            raise _WrongError("ERR 1 BUSY", f"END {msg.count}: the series ended before (too fast?)")
        if not is_err(msg, 1):
            raise _WrongError(
                f"ERR 1 BUSY to 'MEAS 1 {self.rate:g}'", text_of(msg, self.line_timeout)
            )
        return "ERR 1 BUSY while the series runs"

    def _stop(self) -> str:
        if self.series is None:
            self._start_long()
        self.wire.send("STOP")
        msg = self._until_reply()
        if not isinstance(msg, Ok):
            raise _WrongError("OK to 'STOP'", text_of(msg, self.line_timeout))
        end = self._until_reply()
        if not isinstance(end, End) or not 0 < end.count < LONG:
            raise _WrongError(
                f"END <k> after OK to 'STOP', k < {LONG}", text_of(end, self.line_timeout)
            )
        received, self.series = self.series, None
        if end.count != received:
            raise _WrongError(f"END {received} ({received} points sent)", f"END {end.count}")
        return f"OK, END {end.count}"

    # ---------------------------------------------------------------- refusals

    def _unknown(self) -> str:
        return self._refused("XYZZY", 4)

    def _malformed(self) -> str:
        for request in (f"MEAS abc {self.rate:g}", "SMR RRR99", "ENV T=abc P=1013.25 RH=45.0"):
            self._refused(request, 3)
        return "ERR 3 to 'MEAS abc', 'SMR RRR99', 'ENV T=abc'"

    def _too_long(self) -> str:
        got = self._refused(b"X" * 300, 3)
        msg = self.wire.ask("*IDN?")
        if not isinstance(msg, Ok) or msg.payload != self.idn:
            raise _WrongError(f"OK {self.idn} to '*IDN?' after it", text_of(msg, self.wire.timeout))
        return got

    # ---------------------------------------------------------------- version 2

    def _proto(self, version: int) -> str:
        msg = self._expect(f"PROTO {version}", f"OK {version} to 'PROTO {version}'")
        if msg.payload.strip() != str(version):
            raise _WrongError(f"OK {version} to 'PROTO {version}'", text_of(msg, 0))
        return f"OK {version}"

    def _measure_2(self) -> str:
        points = self._series(SHORT, 2)
        sigmas = []
        for p in points:
            assert p.cov is not None and p.air is not None
            c = covariance(p.cov)
            eig = np.linalg.eigvalsh(c)
            if eig.min() < -1e-9 - 1e-6 * abs(eig.max()):
                expected = "a positive semi-definite covariance"
                raise _WrongError(expected, f"PT {p.i}: {p.cov}, eigenvalues {eig.tolist()}")
            ranges = RANGES.values()
            if not all(lo <= v <= hi for v, (lo, hi) in zip(p.air, ranges, strict=True)):
                expected = "air within 0–40 °C, 600–1100 hPa, 0–95 %"
                raise _WrongError(expected, f"PT {p.i}: T {p.air[0]} P {p.air[1]} RH {p.air[2]}")
            sigmas.append(np.sqrt(np.clip(np.diag(c), 0.0, None)))
        s = np.concatenate(sigmas)
        T, P, RH = points[0].air or (0.0, 0.0, 0.0)
        return (
            f"{SHORT} points with covariance (σ {s.min():.4f}–{s.max():.4f} mm) and air "
            f"({T:g} °C, {P:g} hPa, {RH:g} %)"
        )

    def _proto_unknown(self) -> str:
        return self._refused(f"PROTO {self.versions[-1] + 1}", 3)

    def _proto_1(self) -> str:
        self._proto(1)
        self._series(1, 1)
        return "OK 1; MEAS in version 1's form"

    def _fresh(self) -> str:
        self._proto(2)
        self.wire.close()
        self.wire.open()
        self._series(1, 1)
        return "a new connection after 'PROTO 2' measures in version 1's form"


def check_conformance(
    address: str,
    *,
    timeout: float = 5.0,
    rate_hz: float = 10.0,
    init_timeout: float = 60.0,
    transport: Transport | None = None,
) -> Conformance:
    """Run every check against the tracker at ``address`` (a pyserial URL)."""
    check = ConformanceCheck(
        address, timeout=timeout, rate_hz=rate_hz, init_timeout=init_timeout, transport=transport
    )
    return check.run()
