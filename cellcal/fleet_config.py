"""The ``[fleet]`` table: where a cell replicates its campaigns (a central PostgreSQL)
and the name it has there. The URL is libpq's; its password never is in the
configuration: libpq reads it from ``PGPASSFILE`` (``~/.pgpass``) or a service file."""

from __future__ import annotations

import re
from typing import Annotated
from urllib.parse import parse_qs, urlsplit

from pydantic import Field, field_validator

from cellcal.device_options import Strict

#: a cell's or a line's name in the fleet
NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


def url_problem(url: str) -> str | None:
    """What is wrong with a fleet database URL, in words (None: nothing)."""
    parts = urlsplit(url)
    if parts.scheme not in ("postgresql", "postgres"):
        return f"{url[:60]!r} is not a libpq URL (postgresql://USER@HOST:PORT/DATABASE)"
    if parts.password is not None or "password" in parse_qs(parts.query):
        return (
            "a password in the URL; libpq takes it from PGPASSFILE (~/.pgpass) or a "
            "service file, never from the configuration"
        )
    if any(not c.isprintable() or c.isspace() for c in url):
        return "the URL holds spaces or control characters"
    return None


class FleetConfig(Strict):
    """``database``: the central PostgreSQL (a libpq URL without a password); ``cell``:
    this cell's name there, unique in the fleet; ``line``: its group on the fleet page."""

    database: str
    cell: Annotated[str, Field(pattern=NAME)]
    line: Annotated[str, Field(pattern=NAME)] | None = None

    @field_validator("database")
    @classmethod
    def _url(cls, value: str) -> str:
        problem = url_problem(value)
        if problem is not None:
            raise ValueError(problem)
        return value


def redacted(url: str) -> str:
    """A URL as it may be shown (a password, if one came from elsewhere, hidden)."""
    return re.sub(r"://([^:/@]+):[^@/]*@", r"://\1:***@", url)
