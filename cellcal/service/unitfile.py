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
import textwrap
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from cellcal.errors import CampaignError

UNIT_NAME = "cellcal.service"
FIELDS = ("venv", "config", "user", "protect_home")
#: the checks between calibrations on a schedule (``--check-every``): a timer that starts
#: a one-shot service, which queues a check in the cell service
CHECK_SERVICE, CHECK_TIMER = "cellcal-check.service", "cellcal-check.timer"
CHECK_FIELDS = ("venv", "user", "protect_home", "every")
#: a systemd time span: numbers with units (``7d``, ``12h 30min``, ``1w``)
_SPAN = re.compile(
    r"^(\d+\s*(us|usec|ms|msec|s|sec|second|seconds|m|min|minute|minutes|h|hr|hour|hours|"
    r"d|day|days|w|week|weeks|M|month|months|y|year|years)\s*)+$"
)
#: What systemd accepts in a path it executes or passes on without quoting.
_PLAIN = re.compile(r"^/[A-Za-z0-9._/+-]+$")


@dataclass(frozen=True)
class Verification:
    """``systemd-analyze verify`` on a unit: ``ran`` is False when the tool is absent."""

    ran: bool
    ok: bool
    message: str


def template(name: str = UNIT_NAME) -> str:
    return (resources.files("cellcal") / "data" / name).read_text()


def _values(venv: Path, config: Path, user: str) -> dict[str, str]:
    """The fields every unit of the installation is filled in with. ``ProtectHome`` is
    ``read-only`` when the venv or the configuration lives under /home or /root (the
    service must read them), else ``yes``."""
    for what, path in (("--venv", venv), ("--config", config)):
        if not _PLAIN.match(str(path)):
            raise CampaignError(
                f"{what} {path}: give an absolute path of letters, digits and . _ - + / "
                "(systemd would split or expand anything else)"
            )
    if not re.match(r"^[a-z_][a-z0-9_-]*$", user):
        raise CampaignError(f"--user {user!r}: not a system user name")
    home = any(str(p).startswith(("/home/", "/root/")) for p in (venv, config))
    return {
        "venv": str(venv),
        "config": str(config),
        "user": user,
        "protect_home": "read-only" if home else "yes",
    }


def _filled(text: str, values: dict[str, str], fields: tuple[str, ...]) -> str:
    for key in fields:
        text = text.replace("${" + key + "}", values[key])
    left = re.findall(r"\$\{(\w+)\}", text)
    if left:
        raise CampaignError(f"the unit template has unknown fields: {', '.join(left)}")
    return text


def render(venv: Path, config: Path, user: str) -> str:
    """The unit for this installation."""
    text = _rendered_header(UNIT_NAME, template(), venv, config, user)
    return _filled(text, _values(venv, config, user), FIELDS)


def render_check(venv: Path, config: Path, user: str, every: str) -> dict[str, str]:
    """The timer and the one-shot service that queue a check every ``every`` (a systemd
    time span), by file name."""
    span = " ".join(every.split())
    if not _SPAN.match(span):
        raise CampaignError(
            f"--check-every {every!r}: a systemd time span, e.g. 7d, 12h, 1w, 2d 12h"
        )
    values = {**_values(venv, config, user), "every": span}
    return {
        name: _filled(
            _rendered_header(name, template(name), venv, config, user), values, CHECK_FIELDS
        )
        for name in (CHECK_SERVICE, CHECK_TIMER)
    }


def _rendered_header(name: str, text: str, venv: Path, config: Path, user: str) -> str:
    """The template's opening comment (about the template and its fields) replaced by
    one about this rendered copy of unit ``name``."""
    body = text[text.index("[Unit]") :]
    what = {
        UNIT_NAME: "The cell service's systemd unit",
        CHECK_SERVICE: "The check between calibrations (docs/checks.md): started by"
        " cellcal-check.timer, it queues a check in the cell service, which runs it after"
        " the campaign under way",
        CHECK_TIMER: "The timer that starts cellcal-check.service (a check between calibrations)",
    }[name]
    comment = (
        f"{what}. Rendered by `cellcal service install` from the bundled template for venv"
        f" {venv}, configuration {config}, user {user} (see docs/service.md). After editing"
        " it: sudo systemctl daemon-reload."
    )
    return (
        "".join(
            f"# {line}\n"
            for line in textwrap.wrap(comment, 86, break_long_words=False, break_on_hyphens=False)
        )
        + body
    )


def verify(
    text: str, tool: str | None = None, others: dict[str, str] | None = None
) -> Verification:
    """``systemd-analyze verify`` on the rendered unit (and ``others``, the check's timer
    and service, by file name), in a folder of their own."""
    exe = tool or shutil.which("systemd-analyze")
    if exe is None:
        return Verification(False, True, "systemd-analyze is not installed: not verified")
    with tempfile.TemporaryDirectory(prefix="cellcal-unit-") as folder:
        path = Path(folder) / UNIT_NAME
        path.write_text(text)
        paths = [str(path)]
        for name, other in (others or {}).items():
            (Path(folder) / name).write_text(other)
            paths.append(str(Path(folder) / name))
        try:
            done = subprocess.run(
                [exe, "verify", "--man=no", *paths],
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
