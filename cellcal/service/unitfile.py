"""The service's systemd unit: the bundled template (``config/cellcal.service``) filled
in for one installation, and ``systemd-analyze verify`` on the result.

``systemd-analyze verify`` exits 0 on an unknown key, so a unit is only accepted when
it exits 0 *and* says nothing on stderr.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from cellcal.errors import CampaignError

UNIT_NAME = "cellcal.service"
FIELDS = ("venv", "config", "user", "protect_home")
#: What systemd accepts in a path it executes or passes on without quoting.
_PLAIN = re.compile(r"^/[A-Za-z0-9._/+-]+$")


@dataclass(frozen=True)
class Verification:
    """``systemd-analyze verify`` on a unit: ``ran`` is False when the tool is absent."""

    ran: bool
    ok: bool
    message: str


def template() -> str:
    return (resources.files("cellcal") / "data" / UNIT_NAME).read_text()


def render(venv: Path, config: Path, user: str) -> str:
    """The unit for this installation. ``ProtectHome`` is ``read-only`` when the venv or
    the configuration lives under /home or /root (the service must read them), else
    ``yes``."""
    for what, path in (("--venv", venv), ("--config", config)):
        if not _PLAIN.match(str(path)):
            raise CampaignError(
                f"{what} {path}: give an absolute path of letters, digits and . _ - + / "
                "(systemd would split or expand anything else)"
            )
    if not re.match(r"^[a-z_][a-z0-9_-]*$", user):
        raise CampaignError(f"--user {user!r}: not a system user name")
    home = any(str(p).startswith(("/home/", "/root/")) for p in (venv, config))
    values = {
        "venv": str(venv),
        "config": str(config),
        "user": user,
        "protect_home": "read-only" if home else "yes",
    }
    text = _rendered_header(template(), venv, config, user)
    for key in FIELDS:
        text = text.replace("${" + key + "}", values[key])
    left = re.findall(r"\$\{(\w+)\}", text)
    if left:
        raise CampaignError(f"the unit template has unknown fields: {', '.join(left)}")
    return text


def _rendered_header(text: str, venv: Path, config: Path, user: str) -> str:
    """The template's opening comment (about the template and its fields) replaced by
    one about this rendered copy."""
    body = text[text.index("[Unit]") :]
    return (
        "# The cell service's systemd unit, rendered by `cellcal service install` from the\n"
        f"# bundled template for venv {venv}, configuration {config}, user {user}\n"
        "# (see docs/service.md). After editing it: sudo systemctl daemon-reload.\n" + body
    )


def verify(text: str, tool: str | None = None) -> Verification:
    """``systemd-analyze verify`` on the rendered unit, in a folder of its own."""
    exe = tool or shutil.which("systemd-analyze")
    if exe is None:
        return Verification(False, True, "systemd-analyze is not installed: not verified")
    with tempfile.TemporaryDirectory(prefix="cellcal-unit-") as folder:
        path = Path(folder) / UNIT_NAME
        path.write_text(text)
        try:
            done = subprocess.run(
                [exe, "verify", "--man=no", str(path)],
                capture_output=True,
                text=True,
                timeout=60,
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            return Verification(True, False, f"systemd-analyze verify did not run: {exc}")
    said = " | ".join(line for line in done.stderr.splitlines() if line.strip())
    if done.returncode != 0 or said:
        message = said or f"systemd-analyze verify exited {done.returncode}"
        return Verification(True, False, message.replace(folder, "").replace("//", "/"))
    return Verification(True, True, "systemd-analyze verify: no complaint")
