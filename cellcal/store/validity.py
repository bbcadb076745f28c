"""The models a cell has carried and the checks made of them (schema 6): a mixin of
:class:`~cellcal.store.database.Store`, which owns the connection and the transactions.

A calibration's model is valid from the moment its analysis is stored until a newer
model replaces it or a check finds the robot out of its limits (``valid_until``, with
``ended_by`` saying which); the current model is the one still valid. A check never
writes a model: it records its figures in ``checks``, naming the model it compared with
(its id, or only its digest for a model given as a file)."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from cellcal.store.connection import loads
from cellcal.store.schema import model_digest, utc_now


class _Transaction(Protocol):
    def __enter__(self) -> sqlite3.Connection: ...

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None: ...


@dataclass(frozen=True)
class ModelRow:
    """A calibrated model as the cell carried it: the campaign that made it, when it
    became valid and when it ended (None: it is current), and why it ended."""

    id: int
    campaign_id: int
    created: str
    valid_from: str
    valid_until: str | None
    ended_by: str | None
    digest: str
    model_toml: str

    @property
    def current(self) -> bool:
        return self.valid_until is None


@dataclass(frozen=True)
class CheckRow:
    """A check's figures: the model it compared with (``model_id`` None: a model given as
    a file, known by its digest), the RMS and largest error of its poses against its
    limits (mm), its verdict and the cause it named."""

    id: int
    campaign_id: int
    model_id: int | None
    model_digest: str
    created: str
    n_poses: int
    rms_mm: float
    max_mm: float
    warning_mm: float
    limit_mm: float
    verdict: str
    cause: str | None
    errors_mm: tuple[float, ...]


_MODEL_COLUMNS = "id, campaign_id, created, valid_from, valid_until, ended_by, digest, model_toml"
_CHECK_COLUMNS = (
    "id, campaign_id, model_id, model_digest, created, n_poses, rms_mm, max_mm, warning_mm, "
    "limit_mm, verdict, cause, errors_mm"
)


class ValidityTables:
    """Writes and reads the ``models`` and ``checks`` tables."""

    conn: sqlite3.Connection
    path: str
    transaction: Callable[[], _Transaction]

    def _older(self) -> bool:
        """A file older than schema 6, opened read-only as it is: no models, no checks."""
        return int(self.conn.execute("PRAGMA user_version").fetchone()[0]) < 6

    def add_model(self, campaign_id: int, model_toml: str, when: str | None = None) -> int:
        """Record a calibration's model as the cell's current one (ending the previous
        one at the same moment); inside the caller's transaction when there is one."""
        now = when or utc_now()
        with self.transaction():
            cur = self.conn.execute(
                """INSERT INTO models (campaign_id, created, valid_from, model_toml, digest)
                VALUES (?, ?, ?, ?, ?)""",
                (campaign_id, now, now, model_toml, model_digest(model_toml)),
            )
            new = int(cur.lastrowid or 0)
            self.conn.execute(
                """UPDATE models SET valid_until = ?, ended_by = ?
                WHERE valid_until IS NULL AND id != ?""",
                (now, f"model {new} (campaign {campaign_id})", new),
            )
            return new

    def end_model(self, model_id: int, ended_by: str, when: str | None = None) -> None:
        """End a model's validity (a failed check); a model already ended keeps its end."""
        with self.transaction():
            self.conn.execute(
                """UPDATE models SET valid_until = ?, ended_by = ?
                WHERE id = ? AND valid_until IS NULL""",
                (when or utc_now(), ended_by, model_id),
            )

    def models(self) -> list[ModelRow]:
        """Every model, the oldest first (none in a file older than schema 6)."""
        if self._older():
            return []
        rows = self.conn.execute(f"SELECT {_MODEL_COLUMNS} FROM models ORDER BY id").fetchall()
        return [ModelRow(*r) for r in rows]

    def model(self, model_id: int) -> ModelRow | None:
        if self._older():
            return None
        row = self.conn.execute(
            f"SELECT {_MODEL_COLUMNS} FROM models WHERE id = ?", (model_id,)
        ).fetchone()
        return None if row is None else ModelRow(*row)

    def current_model(self) -> ModelRow | None:
        """The model still valid (None: none was made, or the last one was ended)."""
        if self._older():
            return None
        row = self.conn.execute(
            f"SELECT {_MODEL_COLUMNS} FROM models WHERE valid_until IS NULL "
            "ORDER BY id DESC LIMIT 1"
        ).fetchone()
        return None if row is None else ModelRow(*row)

    def model_of_campaign(self, campaign_id: int) -> ModelRow | None:
        """The model a calibration campaign made (None: it made none)."""
        if self._older():
            return None
        row = self.conn.execute(
            f"SELECT {_MODEL_COLUMNS} FROM models WHERE campaign_id = ? ORDER BY id DESC LIMIT 1",
            (campaign_id,),
        ).fetchone()
        return None if row is None else ModelRow(*row)

    def add_check(
        self,
        campaign_id: int,
        model_id: int | None,
        digest: str,
        *,
        rms_mm: float,
        max_mm: float,
        warning_mm: float,
        limit_mm: float,
        verdict: str,
        cause: str | None,
        errors_mm: tuple[float, ...],
        ends_model: bool,
    ) -> None:
        """Record a check's figures; with ``ends_model`` (the robot is out of its limits)
        the model it checked is ended in the same transaction."""
        now = utc_now()
        with self.transaction():
            self.conn.execute(
                f"""INSERT INTO checks ({_CHECK_COLUMNS.removeprefix("id, ")})
                VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
                (
                    campaign_id,
                    model_id,
                    digest,
                    now,
                    len(errors_mm),
                    rms_mm,
                    max_mm,
                    warning_mm,
                    limit_mm,
                    verdict,
                    cause,
                    json.dumps([round(e, 9) for e in errors_mm]),
                ),
            )
            if ends_model and model_id is not None:
                self.end_model(model_id, f"check campaign {campaign_id} ({verdict})", now)

    def checks(self, model_id: int | None = None) -> list[CheckRow]:
        """Every check (of one model), the oldest first."""
        if self._older():
            return []
        where, args = ("WHERE model_id = ?", (model_id,)) if model_id is not None else ("", ())
        rows = self.conn.execute(
            f"SELECT {_CHECK_COLUMNS} FROM checks {where} ORDER BY id", args
        ).fetchall()
        return [self._check_row(r) for r in rows]

    def check_of_campaign(self, campaign_id: int) -> CheckRow | None:
        if self._older():
            return None
        row = self.conn.execute(
            f"SELECT {_CHECK_COLUMNS} FROM checks WHERE campaign_id = ?", (campaign_id,)
        ).fetchone()
        return None if row is None else self._check_row(row)

    def _check_row(self, r: tuple[object, ...]) -> CheckRow:
        errors = loads(self.path, str(r[12]), f"check {r[0]}'s errors")
        values = (*r[:12], tuple(float(e) for e in errors))
        return CheckRow(*values)  # type: ignore[arg-type]
