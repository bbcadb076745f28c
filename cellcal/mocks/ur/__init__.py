"""The UR twin: a controller that speaks RTDE, the dashboard server and the script port on
their real ports."""
