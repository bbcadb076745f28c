"""The versions of the tracker line protocol (``docs/tracker.md``) on the client's side:
which one a connection speaks, and the samples of a series in either.

A tracker speaks version 1 on every new connection until it is asked for another with
``PROTO <v>``; ``PROTO?`` lists the versions it speaks (``OK 1,2``), and a version 1
tracker, which has no such request, answers ``ERR 4 UNKNOWN_COMMAND``. Version 2 adds to
each ``PT`` line the sample's covariance and the air the tracker compensated it with.
A client that does not ask (every version 1 client) never sees a version 2 line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers.base import Series
from cellcal.drivers.tracker_protocol import (
    Ok,
    Point,
    TrackerError,
    TrackerNotImplementedError,
    TrackerUnknownCommandError,
    parse_versions,
)

#: The versions cellcal's driver speaks.
SUPPORTED = (1, 2)
#: The upper triangle of a 3×3 covariance, row by row: xx xy xz yy yz zz.
UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def covariance(terms: tuple[float, ...]) -> Array:
    """The symmetric 3×3 covariance (mm²) of the six upper-triangle terms of a point."""
    out = np.zeros((3, 3))
    out[UPPER] = terms
    out[UPPER[1], UPPER[0]] = terms
    return out


def announced(ask: Callable[[str], Ok], where: str) -> tuple[tuple[int, ...], str]:
    """The versions the tracker speaks, asked with ``PROTO?``, and how it answered: a
    tracker that does not know the request (``ERR 4``, or ``ERR 2``) speaks version 1."""
    try:
        ok = ask("PROTO?")
    except (TrackerUnknownCommandError, TrackerNotImplementedError) as exc:
        return (1,), f"ERR {exc.code}"
    versions = parse_versions(ok.payload)
    if versions is None:
        raise TrackerError(
            f"{where}: 'PROTO?' answered 'OK {ok.payload}': not a list of versions such as 'OK 1,2'"
        )
    return versions, f"OK {ok.payload.strip()}"


def negotiate(ask: Callable[[str], Ok], wanted: int | None, where: str) -> int:
    """The version this connection speaks from now on: ``wanted`` (1 asks nothing), or
    with None the highest the tracker announces that cellcal speaks. ``ask`` sends one
    request and returns its OK (raising the tracker's ERR as an exception)."""
    if wanted == 1:
        return 1
    versions, answer = announced(ask, where)
    version = wanted if wanted is not None else max(v for v in versions if v in SUPPORTED)
    if version not in versions:
        raise TrackerError(
            f"{where}: protocol = {version}, but the tracker speaks line protocol version "
            f"{', '.join(map(str, versions))} ('PROTO?' answered {answer}): set protocol = 1, "
            "or use a bridge that speaks version 2"
        )
    if version != 1:
        ok = ask(f"PROTO {version}")
        if ok.payload.strip() != str(version):
            raise TrackerError(f"{where}: 'PROTO {version}' answered 'OK {ok.payload}'")
    return version


@dataclass
class Received:
    """The points of one measurement, across its re-takes: host and device times,
    positions, and in version 2 each point's covariance and air."""

    host: list[float] = field(default_factory=list)
    device: list[float] = field(default_factory=list)
    xyz: list[tuple[float, float, float]] = field(default_factory=list)
    cov: list[tuple[float, ...]] = field(default_factory=list)
    air: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, host_time: float, point: Point) -> None:
        self.host.append(host_time)
        self.device.append(point.t)
        self.xyz.append((point.x, point.y, point.z))
        if point.cov is not None and point.air is not None:
            self.cov.append(point.cov)
            self.air.append(point.air)

    def series(self, sensor: str, *, retries: int, note: str) -> Series:
        """The Series; ``cov`` (N×3×3) and ``meteo`` (N×3) when every point carried
        them (a series whose re-takes changed version has neither)."""
        n = len(self.xyz)
        whole = n > 0 and len(self.cov) == n
        return Series(
            sensor,
            np.array(self.host),
            np.array(self.device),
            np.array(self.xyz, dtype=np.float64).reshape(-1, 3),
            retries=retries,
            note=note,
            cov=np.array([covariance(c) for c in self.cov]) if whole else None,
            meteo=np.array(self.air, dtype=np.float64) if whole else None,
        )
