"""What the fleet's page reads from the central PostgreSQL: per cell its line and last
sending, its current model, its checks, and its calibrations' accuracy before and after
(the validation RMS, read inside the server from each campaign's stored summary), in a
few aggregate queries whatever the size of the fleet (no sample leaves the server)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import psycopg

from cellcal.store.fleet_server import FleetError, connected, require_schema


@dataclass(frozen=True)
class FleetCell:
    cell: str
    line: str | None
    last_seen: datetime


@dataclass(frozen=True)
class FleetModel:
    """A cell's current model: its id and campaign in the cell, since when, its digest."""

    cell: str
    id: int
    campaign_id: int
    valid_from: str
    digest: str


@dataclass(frozen=True)
class FleetCheck:
    cell: str
    campaign_id: int
    model_id: int | None
    created: str
    rms_mm: float
    max_mm: float
    warning_mm: float
    limit_mm: float
    verdict: str
    cause: str | None


@dataclass(frozen=True)
class FleetCalibration:
    """A calibration campaign's validation RMS before and after (mm; None where its
    summary has none: refused, or of an earlier cellcal)."""

    cell: str
    campaign_id: int
    finished: str | None
    before_mm: float | None
    after_mm: float | None


@dataclass(frozen=True)
class FleetData:
    cells: tuple[FleetCell, ...]
    models: tuple[FleetModel, ...]
    checks: tuple[FleetCheck, ...]
    calibrations: tuple[FleetCalibration, ...]
    now: datetime


def _where(lines: Sequence[str], cells: Sequence[str], alias: str = "") -> tuple[str, list[Any]]:
    """A filter on the cells asked for: by line (through ``cells``) or by name."""
    prefix = f"{alias}." if alias else ""
    parts, args = [], []
    if cells:
        parts.append(f"{prefix}cell = ANY(%s)")
        args.append(list(cells))
    if lines:
        parts.append(f"{prefix}cell IN (SELECT cell FROM cells WHERE line = ANY(%s))")
        args.append(list(lines))
    return (" WHERE " + " AND ".join(parts)) if parts else "", args


def read_fleet(url: str, lines: Sequence[str] = (), cells: Sequence[str] = ()) -> FleetData:
    """Everything the fleet's page shows, of the cells asked for (every cell: none)."""
    with connected(url, "cellcal fleet report") as conn:
        require_schema(conn, url)
        return _read(conn, lines, cells)


def _read(conn: psycopg.Connection[Any], lines: Sequence[str], cells: Sequence[str]) -> FleetData:
    where, args = _where(lines, cells)
    found = conn.execute(
        f"SELECT cell, line, last_seen FROM cells{where} ORDER BY line NULLS LAST, cell", args
    ).fetchall()
    if not found and (lines or cells):
        raise FleetError(
            "no cell of the fleet matches "
            + " and ".join(
                f"{what} {', '.join(v)}" for what, v in (("--line", lines), ("--cell", cells)) if v
            )
        )
    models = conn.execute(
        f"""SELECT cell, id, campaign_id, valid_from, digest FROM models
        {where or " WHERE true"} AND valid_until IS NULL ORDER BY cell, id""",
        args,
    ).fetchall()
    checks = conn.execute(
        f"""SELECT cell, campaign_id, model_id, created, rms_mm, max_mm, warning_mm,
        limit_mm, verdict, cause FROM checks{where} ORDER BY cell, created""",
        args,
    ).fetchall()
    cwhere, cargs = _where(lines, cells, "c")
    calibrations = conn.execute(
        f"""SELECT c.cell, c.id, c.finished,
            (r.summary::jsonb -> 'validation_before' ->> 'rms_mm')::float8,
            (r.summary::jsonb -> 'validation_after' ->> 'rms_mm')::float8
        FROM campaigns c LEFT JOIN LATERAL (
            SELECT summary FROM reports WHERE cell = c.cell AND campaign_id = c.id
            ORDER BY id DESC LIMIT 1) r ON true
        {cwhere or " WHERE true"} AND c.kind = 'calibration' AND c.status = 'complete'
        ORDER BY c.cell, c.id""",
        cargs,
    ).fetchall()
    now = conn.execute("SELECT now()").fetchone()
    assert now is not None
    return FleetData(
        tuple(FleetCell(*r) for r in found),
        tuple(FleetModel(*r) for r in models),
        tuple(FleetCheck(*r) for r in checks),
        tuple(FleetCalibration(*r) for r in calibrations),
        now[0],
    )
