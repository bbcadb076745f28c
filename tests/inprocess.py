"""``cellcal ARGS`` run in the test's own process, through the console script's entry
point (``cellcal.cli.main``): its exit code, stdout and stderr, as a subprocess would
give them, without a second interpreter's start and imports (a second or two a call).

For the tests about what a command prints and returns. The tests about the process
itself (signals, exit codes of the real executable, what a fresh interpreter imports,
configuration warnings printed once per process) keep running ``python -m cellcal``."""

from __future__ import annotations

import contextlib
import io
import logging
import subprocess

from cellcal.cli import main


def cellcal(*args: object) -> subprocess.CompletedProcess[str]:
    """The command's exit code and streams; the logging it set up for itself (a handler
    on its redirected stderr) is undone, so later tests do not log into a stream that
    is gone."""
    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
        finally:
            root.handlers[:] = handlers
            root.setLevel(level)
    return subprocess.CompletedProcess(
        ["cellcal", *map(str, args)], code, out.getvalue(), err.getvalue()
    )
