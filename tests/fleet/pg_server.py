"""A real PostgreSQL server of the tests' own: Debian's package, a cluster initdb'd in a
temporary folder, listening on a loopback address and a free port, password
authentication (scram-sha-256) on TCP as a fleet's server has it, stopped and removed at
the end. PostgreSQL refuses to run as root: as root (CI) its programs run as the
``postgres`` user Debian's package creates.

``make test`` installs the package (scripts/debs.sh); where it is missing the fleet tests
skip with that reason."""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

#: the fleet tests' own loopback addresses: the server, and the proxy that cuts the network
HOST = "127.0.0.210"
PROXY_HOST = "127.0.0.211"
ADMIN, PASSWORD = "fleet_admin", "fleet-secret-1"
DATABASE = "fleet"


def _bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if found:
        return Path(found[-1]).parent
    exe = shutil.which("initdb")
    return Path(exe).resolve().parent if exe else None


def free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class PgServer:
    """One cluster: :meth:`start`, :meth:`stop`, :meth:`restart`, :meth:`remove`;
    :meth:`url` the libpq URL a cell's configuration would hold (no password: it comes
    from the ``PGPASSFILE`` the tests set, :meth:`passfile`)."""

    def __init__(self) -> None:
        bin_dir = _bin()
        if bin_dir is None:
            pytest.skip("PostgreSQL is not installed (make test installs Debian's postgresql)")
        self.bin = bin_dir
        self.as_postgres: list[str] = []
        if os.geteuid() == 0:
            try:
                import pwd

                pwd.getpwnam("postgres")
            except KeyError:
                pytest.skip("PostgreSQL refuses root and there is no postgres user to run it")
            self.as_postgres = ["runuser", "-u", "postgres", "--"]
        self.root = Path(tempfile.mkdtemp(prefix="cellcal-pg-"))
        self.data = self.root / "data"
        self.port = free_port(HOST)
        pwfile = self.root / "pw"
        pwfile.write_text(PASSWORD + "\n")
        if self.as_postgres:
            shutil.chown(self.root, "postgres")
            shutil.chown(pwfile, "postgres")
        self._run(
            "initdb", "-D", str(self.data), "-U", ADMIN, f"--pwfile={pwfile}",
            "--auth-local=trust", "--auth-host=scram-sha-256", "-E", "UTF8", "--no-sync",
        )  # fmt: skip
        pwfile.unlink()

    def _run(self, program: str, *args: str) -> str:
        done = subprocess.run(
            [*self.as_postgres, str(self.bin / program), *args],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        if done.returncode != 0:
            raise RuntimeError(f"{program} {' '.join(args)}: {done.stdout}{done.stderr}")
        return done.stdout

    def start(self) -> None:
        options = (
            f"-c listen_addresses={HOST} -p {self.port} -k {self.root} -c fsync=off "
            "-c synchronous_commit=off -c full_page_writes=off"
        )
        self._run("pg_ctl", "-D", str(self.data), "-o", options, "-l", str(self.root / "log"),
                  "-w", "-t", "60", "start")  # fmt: skip

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def restart(self) -> None:
        self.stop()
        self.start()

    def psql(self, sql: str, database: str = "postgres") -> str:
        """``sql`` run over the cluster's own socket as its admin (trust)."""
        return self._run(
            "psql", "-h", str(self.root), "-p", str(self.port), "-U", ADMIN, "-d", database,
            "-X", "-A", "-t", "-v", "ON_ERROR_STOP=1", "-c", sql,
        )  # fmt: skip

    def create_database(self, name: str = DATABASE) -> None:
        self.psql(f"CREATE DATABASE {name}")

    def url(self, database: str = DATABASE, host: str = HOST, port: int | None = None) -> str:
        return f"postgresql://{ADMIN}@{host}:{port or self.port}/{database}"

    def passfile(self, folder: Path, password: str = PASSWORD) -> Path:
        """A libpq password file (``PGPASSFILE``) for this server, mode 600."""
        path = folder / "pgpass"
        path.write_text(f"*:*:*:{ADMIN}:{password}\n")
        path.chmod(0o600)
        return path

    def remove(self) -> None:
        with contextlib.suppress(RuntimeError):  # already stopped
            self.stop()
        shutil.rmtree(self.root, ignore_errors=True)
