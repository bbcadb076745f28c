"""The dashboard server of the UR twin (TCP 29999): one ``\\n``-terminated line per
request, one line per answer, after the welcome line. Stdlib only.

The commands and answers of a PolyScope 5.11 (e-Series) dashboard server, in UR's
words; the robot model is a UR10 (what a UR10e reports):

========================================  =================================================
``load <file.urp>``                       ``Loading program: <file>`` /
                                          ``File not found: <file>`` /
                                          ``Error while loading program: <file>`` (a
                                          program is running, or not a .urp)
``play``                                  ``Starting program`` / ``Failed to execute: play``
``stop``                                  ``Stopped`` / ``Failed to execute: stop`` (no
                                          program running, paused or stopping)
``pause``                                 ``Pausing program`` / ``Failed to execute: pause``
``running``                               ``Program running: true|false``
``programState``                          ``STOPPED|PLAYING|PAUSED <program name>``
``get loaded program``                    ``Loaded program: <path>`` / ``No program loaded``
``isProgramSaved``                        ``true <program name>`` / ``false ...``
``robotmode``                             ``Robotmode: <mode>``
``safetymode`` / ``safetystatus``         ``Safetymode: <mode>`` / ``Safetystatus: <status>``
``power on`` / ``power off``              ``Powering on`` / ``Powering off``
``brake release``                         ``Brake releasing``
``unlock protective stop``                ``Protective stop releasing``
``restart safety``                        ``Restarting safety``
``close safety popup``                    ``closing safety popup``
``popup <text>`` / ``close popup``        ``showing popup`` / ``closing popup``
``addToLog <message>``                    ``Added log message`` / ``No log message to add``
``PolyscopeVersion``                      ``URSoftware 5.11.1.108318 (Mar 22 2021)``
``version``                               ``5.11.1.108318``
``get serial number``                     the serial number
``get robot model``                       ``UR10``
``is in remote control``                  ``true``
``get operational mode``                  ``NONE`` (no mode password; ``AUTOMATIC`` /
                                          ``MANUAL`` once set)
``set operational mode <manual|auto..>``  ``Operational mode '<mode>' is set`` /
                                          ``Failed setting operational mode: '<mode>'``
``clear operational mode``                ``No longer controlling the operational mode. ...``
``saveLog``                               ``Log saved to disk``
``quit``                                  ``Disconnected`` (and the server closes)
``shutdown``                              ``Shutting down`` (the twin keeps serving)
anything else                             ``could not understand: '<line>'``
========================================  =================================================

Commands are matched case-insensitively, as the controller does. The twin's program
folder (``/programs``) holds :data:`PROGRAMS`; a relative name is looked up there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cellcal.mocks.ur.controller import (
    CONTROL_SCRIPT,
    IDLE,
    PAUSED,
    PLAYING,
    POWER_OFF,
    ROBOT_MODE_NAMES,
    RUNNING,
    RUNTIME_NAMES,
    STOPPED,
    STOPPING,
)

if TYPE_CHECKING:
    from cellcal.mocks.ur.controller import Controller

DASHBOARD_PORT = 29999
WELCOME = "Connected: Universal Robots Dashboard Server"
POLYSCOPE_VERSION = "URSoftware 5.11.1.108318 (Mar 22 2021)"
SOFTWARE_VERSION = "5.11.1.108318"
ROBOT_MODEL = "UR10"
PROGRAM_DIR = "/programs"
#: The programs in the twin's program folder.
PROGRAMS = ("/programs/default.urp", "/programs/calibration.urp")


class Dashboard:
    """Answers of the dashboard server of one controller (shared by its connections)."""

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.operational_mode = "NONE"

    def answer(self, line: str) -> tuple[str, bool]:
        """The reply to one request line, and whether the server closes the connection."""
        c = self.ctl
        cmd = line.strip().lower()
        head, _, arg = line.strip().partition(" ")
        running = c.runtime_state in (PLAYING, PAUSED, STOPPING)
        name = c.program_name or "<unnamed>"
        simple = {
            "polyscopeversion": POLYSCOPE_VERSION,
            "version": SOFTWARE_VERSION,
            "get serial number": c.serial,
            "get robot model": ROBOT_MODEL,
            "is in remote control": "true",
            "get operational mode": self.operational_mode,
            "running": f"Program running: {'true' if c.runtime_state == PLAYING else 'false'}",
            "programstate": f"{RUNTIME_NAMES.get(c.runtime_state, 'STOPPED')} {name}",
            "robotmode": f"Robotmode: {ROBOT_MODE_NAMES.get(c.robot_mode, 'RUNNING')}",
            "safetystatus": f"Safetystatus: {c.safety_name()}",
            "safetymode": f"Safetymode: {c.safety_name()}",
            "close popup": "closing popup",
            "close safety popup": "closing safety popup",
            "savelog": "Log saved to disk",
            "restart safety": "Restarting safety",
            "shutdown": "Shutting down",
        }
        if cmd in simple:
            return simple[cmd], False
        if cmd == "quit":
            return "Disconnected", True
        if cmd == "stop":
            if not running:
                return "Failed to execute: stop", False
            c.stop_program()
            return "Stopped", False
        if cmd == "play":
            return self._play(), False
        if cmd == "pause":
            if c.runtime_state == PLAYING:
                c.halt()
                c.runtime_state = PAUSED
                return "Pausing program", False
            return "Failed to execute: pause", False
        if cmd == "get loaded program":
            if c.loaded_program:
                return f"Loaded program: {c.loaded_program}", False
            return "No program loaded", False
        if cmd == "isprogramsaved":
            return f"true {c.loaded_program.rsplit('/', 1)[-1] or name}", False
        if cmd == "power on":
            if c.robot_mode == POWER_OFF:
                c.robot_mode = IDLE
            return "Powering on", False
        if cmd == "power off":
            c.stop_program()
            c.robot_mode = POWER_OFF
            return "Powering off", False
        if cmd == "brake release":
            if c.robot_mode != POWER_OFF:
                c.robot_mode = RUNNING
            return "Brake releasing", False
        if cmd == "unlock protective stop":
            c.set_protective(False)
            return "Protective stop releasing", False
        if cmd == "clear operational mode":
            self.operational_mode = "NONE"
            return (
                "No longer controlling the operational mode. Current operational mode: ''.",
                False,
            )
        low = head.lower()
        if low == "load" and arg and not arg.lower().startswith("installation"):
            return self._load(arg.strip()), False
        if low == "popup" and arg:
            return "showing popup", False
        if low == "addtolog":
            return ("Added log message" if arg.strip() else "No log message to add"), False
        if cmd.startswith("set operational mode "):
            mode = line.strip()[len("set operational mode ") :].strip()
            if mode.lower() in ("manual", "automatic"):
                self.operational_mode = mode.upper()
                return f"Operational mode '{mode.lower()}' is set", False
            return f"Failed setting operational mode: '{mode}'", False
        return f"could not understand: '{line}'", False

    def _play(self) -> str:
        c = self.ctl
        if not c.can_run():
            return "Failed to execute: play"
        if c.runtime_state == PAUSED:
            c.runtime_state = PLAYING
            return "Starting program"
        if c.runtime_state == STOPPED and c.loaded_program:
            c.play_loaded()
            return "Starting program"
        if c.runtime_state == STOPPED and c.program_name == CONTROL_SCRIPT:
            c.start_control_loop()
            return "Starting program"
        return "Failed to execute: play"

    def _load(self, file: str) -> str:
        c = self.ctl
        path = file if file.startswith("/") else f"{PROGRAM_DIR}/{file}"
        if path not in PROGRAMS:
            return f"File not found: {file}"
        if c.runtime_state != STOPPED or not path.endswith(".urp"):
            return f"Error while loading program: {file}"
        c.loaded_program = path
        c.program_name = path.rsplit("/", 1)[-1]
        return f"Loading program: {file}"
