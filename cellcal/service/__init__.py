"""The cell service (``cellcal daemon``): the control API, the engine thread (worker),
systemd's notification protocol and unit, the locks, the status page."""
