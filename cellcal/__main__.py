"""``python -m cellcal``. Ctrl-C from this file's first line on is one line and exit
130 (``cellcal.cli``, once loaded, takes over: see its docstring).

A SIGINT that comes before the handler is in place (``signal.signal`` runs a pending
signal's old handler, Python's, first) raises KeyboardInterrupt inside this module: it
is caught here and said the same way, never a traceback."""

try:
    # the interpreter's own, loaded at start-up: installing the handler waits for no import
    import _signal  # type: ignore[import-not-found]
    import os

    def _interrupted(signum: int, frame: object) -> None:
        """Ctrl-C while cellcal loads: nothing to unwind."""
        os.write(2, b"cellcal: interrupted\n")
        os._exit(130)

    if __name__ == "__main__":  # not when a spawned process (the camera twin) imports it
        _signal.signal(_signal.SIGINT, _interrupted)
except KeyboardInterrupt:
    import os

    os.write(2, b"cellcal: interrupted\n")
    os._exit(130)

if __name__ == "__main__":
    from cellcal.cli import main

    main()
