"""Where the tests find UR's own RTDE client (UniversalRobots/RTDE_Python_Client_Library).

UR publishes the client on GitHub, not on PyPI, and CI reaches only PyPI. The package
OpenUr 0.3.0 on PyPI carries a copy of it (``openur/rtde/``: ``rtde.py``, ``serialize.py``,
``rtde_config.py``, the CSV writers, under UR's copyright and BSD licence) that is UR's
first GitHub release, 2.7.0 (commit 2fa8991, January 2022), but for the formatting and
one relative import (checked by formatting both and comparing them). ``make test`` runs
this module to download that wheel (pinned by its SHA-256, no dependencies installed:
the rest of OpenUr is not used) and unpack only the ``rtde`` package into
``.venv/ur-rtde-client``.

The tests use, in this order: the checkout named by ``CELLCAL_UR_RTDE_CLIENT`` (UR's
current release, with its ``examples/record.py``), else the unpacked copy. Nothing of
the client is committed to this repository.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "OpenUr==0.3.0"
WHEEL_FILE = "openur-0.3.0-py3-none-any.whl"
WHEEL_SHA256 = "b71dc14ed65413f40230583c2a991f0499ba32b70b8f5785b9ef7beec7b00a7f"
PACKAGE = "openur/rtde/"
DEFAULT_DIR = Path(__file__).resolve().parents[2] / ".venv" / "ur-rtde-client"


def client_dir() -> Path | None:
    """The directory holding UR's ``rtde`` package, or None when there is none."""
    named = os.environ.get("CELLCAL_UR_RTDE_CLIENT", "")
    if named:
        return Path(named)
    return DEFAULT_DIR if (DEFAULT_DIR / "rtde" / "rtde.py").is_file() else None


def fetch(dest: Path) -> None:
    """Download the pinned wheel and unpack UR's ``rtde`` package into ``dest/rtde``."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps"]
        cmd += ["--only-binary", ":all:", "--dest", tmp, WHEEL]
        subprocess.run(cmd, check=True, capture_output=True, timeout=300)
        wheel = Path(tmp) / WHEEL_FILE
        digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
        if digest != WHEEL_SHA256:
            raise RuntimeError(f"{WHEEL_FILE} has SHA-256 {digest}, expected {WHEEL_SHA256}")
        target = dest / "rtde"
        target.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(wheel) as z:
            for name in z.namelist():
                if name.startswith(PACKAGE) and name.endswith(".py"):
                    (target / name[len(PACKAGE) :]).write_bytes(z.read(name))


def main() -> int:
    dest = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_DIR
    if (dest / "rtde" / "rtde.py").is_file():
        return 0
    try:
        fetch(dest)
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"UR's RTDE client ({WHEEL} on PyPI) not fetched: {reason}; its tests skip")
        return 0
    print(f"UR's RTDE client unpacked from {WHEEL} into {dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
