"""``cellcal daemon``: the cell service (``cellcal/service/daemon.py``)."""

from __future__ import annotations

import asyncio
import logging
import os
import sys
from pathlib import Path

import click

from cellcal.commands.output import TIME_SCALE
from cellcal.commands.run import bundled_mock_cell
from cellcal.commands.service_client import socket_path
from cellcal.config import load_config
from cellcal.config_files import check_named_files
from cellcal.errors import InputError
from cellcal.extras import installed
from cellcal.service.daemon import DaemonOptions, serve
from cellcal.service.page import parse_http
from cellcal.store.connection import database_path

#: syslog priorities journald reads from a ``<N>`` prefix (SyslogLevelPrefix=yes).
PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


class _OneLine(logging.Formatter):
    """One line per record (a traceback folded), with journald's priority prefix when
    stderr is the journal."""

    def __init__(self, journal: bool) -> None:
        super().__init__(
            "%(name)s: %(message)s"
            if journal
            else "%(asctime)s %(levelname)s %(name)s: %(message)s"
        )
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        text = " | ".join(super().format(record).splitlines())
        if self.journal:
            return f"<{PRIORITY.get(record.levelno, 6)}>{text}"
        return text


def _logging() -> None:
    journal = bool(os.environ.get("JOURNAL_STREAM"))
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLine(journal))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)


@click.command()
@click.option("--config", "config_path", help="Cell configuration (TOML).")
@click.option(
    "--mock", is_flag=True, help="The simulated cell (twins); without --config, the bundled one."
)
@click.option(
    "--time-scale",
    type=TIME_SCALE,
    default=0.0,
    help="Mock mode: wall seconds per simulated second.",
)
@click.option(
    "--db",
    "db_path",
    help="Campaign database (default: storage.database of the config, else cellcal.db in the "
    "user's data directory: $STATE_DIRECTORY, $XDG_DATA_HOME/cellcal, ~/.local/share/cellcal).",
)
@click.option(
    "--socket",
    "sock",
    help="Control socket (default: $CELLCAL_SOCKET, else /run/cellcal/control.sock); its "
    "folder must be the service's own, writable by it alone.",
)
@click.option(
    "--http",
    "http",
    metavar="HOST:PORT",
    help="Serve the read-only status page here (e.g. 127.0.0.1:8765; port 0: any free).",
)
@click.option(
    "--http-allow-remote",
    is_flag=True,
    help="Let --http name a non-loopback address (the page is read-only, without login).",
)
def daemon(
    config_path: str | None,
    mock: bool,
    time_scale: float,
    db_path: str | None,
    sock: str | None,
    http: str | None,
    http_allow_remote: bool,
) -> int:
    """The cell service: holds the devices, runs queued campaigns, answers the
    ``cellcal campaign`` commands on its control socket. Run by systemd (Type=notify)."""
    # the reports' figures: named now if missing, imported when a report is written
    installed("cellcal daemon", "matplotlib")
    if config_path is None:
        if not mock:
            raise InputError("give --config FILE (or --mock for the bundled simulated cell)")
        config, _ = bundled_mock_cell()
    else:
        config = load_config(config_path)
        check_named_files(config, config_path)
    if time_scale and not mock:
        raise InputError("--time-scale is for mock mode")
    if http_allow_remote and http is None:
        raise InputError("--http-allow-remote goes with --http HOST:PORT")
    address = parse_http(http, http_allow_remote) if http is not None else None
    db = database_path(db_path if db_path is not None else config.storage.database)
    Path(db).parent.mkdir(parents=True, exist_ok=True)
    _logging()
    opts = DaemonOptions(
        config=config,
        config_path=str(Path(config_path).resolve()) if config_path else None,
        mock=mock,
        time_scale=time_scale,
        db_path=str(Path(db).resolve()),
        socket_path=socket_path(sock),
        http=address,
    )
    return asyncio.run(serve(opts))
