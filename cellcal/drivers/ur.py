"""A Universal Robots arm through ur_rtde (``rtde_control``, ``rtde_receive``).

The :class:`~cellcal.drivers.base.Robot` Protocol on top of ur_rtde 1.6: joint moves
(``moveJ``, blocking), joint and TCP readings, stop, close. ur_rtde is imported inside
:meth:`URRobot.connect`, so this module imports without it.

Faults, and what the driver does about them (every one is a one-line
:class:`~cellcal.errors.DeviceError` naming the robot and its host):

* every ur_rtde exception (``RuntimeError``; ``ValueError`` for out-of-range values);
* ``moveJ`` returning False; a protective or emergency stop (checked before and after
  the move); joints more than 1e-3 rad from the target after the move (``getActualQ``
  is given 0.5 s to catch up, as the receive connection may lag the control connection
  by a cycle);
* a call that takes longer than ``timeout_s`` (it runs in a worker thread; the robot
  refuses further commands until that call has returned).

Pitfalls of ur_rtde worth knowing:

* Its constructors hold the GIL while they wait for the controller, so a Python thread
  can neither time them out nor serve them (a simulator must run in another process,
  see :mod:`cellcal.mocks.ur.server`). :meth:`URRobot.connect` therefore first checks,
  with plain sockets and ``timeout_s``, that the three ports (29999, 30003, 30004)
  accept a connection; an unreachable host is then an error within ``timeout_s``, not
  a TCP timeout inside ur_rtde with the interpreter frozen.
* The remote-control check (dashboard ``is in remote control``) is skipped by ur_rtde
  only for ``localhost``/``127.0.0.1``; the driver keeps ur_rtde's default flags
  (upload the control script) and does not disable the check: a real robot must be in
  remote control, and :mod:`cellcal.mocks.ur.server` answers ``true`` on any 127.0.0.x.
* ``moveJ`` cannot be interrupted from another thread: the control script is busy with
  the move, so :meth:`URRobot.stop` takes effect after it (use the pendant, or a
  protective stop, to halt a move in progress).
* In ur_rtde 1.6.5 ``isProtectiveStopped()`` and ``isEmergencyStopped()`` exist on the
  receive interface only; the control interface reads the same bits inside its
  commands. The two interfaces are separate connections, so one may be a cycle behind
  the other: after a refused move the driver looks at the safety bits for up to 0.5 s.
* ``disconnect()`` sleeps 500 ms, and so does each destructor (which disconnects
  again, holding the GIL): :meth:`URRobot.close` takes about 1.5 s.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Literal, TypeVar

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.device_options import Positive, RobotOptions
from cellcal.drivers.base import ROBOT_NAME, DeviceContext, DeviceDescription, label
from cellcal.drivers.stop_and_measure import POSITION_TOLERANCE_RAD, StopAndMeasureRobot
from cellcal.errors import DeviceError, InputError

log = logging.getLogger("cellcal.drivers.ur")

T = TypeVar("T")

#: ur_rtde's limits (rtde_control_interface.h).
MAX_JOINT_VELOCITY = 3.14
MAX_JOINT_ACCELERATION = 40.0
#: How long getActualQ may lag behind the end of a move (s).
SETTLE_S = 0.5
DASHBOARD_PORT = 29999
PORTS = (DASHBOARD_PORT, 30004, 30003)
#: The dashboard's questions of :meth:`URRobot.describe`, answered by every e-Series
#: (PolyScope 5.6 on; an older controller's "could not understand" leaves its field None).
IDENTITY = {
    "model": "get robot model",
    "serial": "get serial number",
    "firmware": "PolyscopeVersion",
}
#: The longest dashboard line read (the twin's and PolyScope's answers are far shorter).
DASHBOARD_LINE = 1024

# Exceptions that pybind11 makes of ur_rtde's C++ exceptions.
_UR_ERRORS = (RuntimeError, ValueError, OverflowError, IndexError)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text or type(e).__name__


def _deg(q: Array) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in np.degrees(q)) + "] deg"


class UROptions(RobotOptions):
    """``[robot]`` with ``driver = "ur"``: ``address`` is the controller's host (the
    ports are fixed: RTDE 30004, dashboard 29999, script 30003); a call (a connect, a
    move) that takes longer than ``move_timeout_s`` has failed."""

    driver: Literal["ur"] = "ur"
    move_timeout_s: Positive = 60.0


class URRobot(StopAndMeasureRobot):
    """A UR arm on ``host`` through ur_rtde. ``move_joints(q, speed)`` moves with
    ``moveJ`` at ``speed × velocity_rad_s`` (leading joint) and ``acceleration_rad_s2``."""

    def __init__(
        self,
        host: str,
        *,
        name: str = "ur-robot",
        timeout_s: float = 30.0,
        velocity_rad_s: float = 1.05,
        acceleration_rad_s2: float = 1.4,
    ) -> None:
        if not host:
            raise InputError("UR robot: the host must not be empty")
        if not (math.isfinite(timeout_s) and timeout_s > 0.0):
            raise InputError(f"UR robot {name!r}: timeout_s must be > 0, not {timeout_s}")
        if not (math.isfinite(velocity_rad_s) and 0.0 < velocity_rad_s <= MAX_JOINT_VELOCITY):
            raise InputError(
                f"UR robot {name!r}: velocity_rad_s must be within (0, {MAX_JOINT_VELOCITY}]"
            )
        if not (
            math.isfinite(acceleration_rad_s2)
            and 0.0 < acceleration_rad_s2 <= MAX_JOINT_ACCELERATION
        ):
            raise InputError(
                f"UR robot {name!r}: acceleration_rad_s2 must be within "
                f"(0, {MAX_JOINT_ACCELERATION}]"
            )
        self.host = host
        self.name = name
        self.timeout_s = float(timeout_s)
        self.velocity_rad_s = float(velocity_rad_s)
        self.acceleration_rad_s2 = float(acceleration_rad_s2)
        self._control: Any = None
        self._receive: Any = None
        self._worker: threading.Thread | None = None

    @classmethod
    def from_options(cls, options: UROptions, context: DeviceContext) -> URRobot:
        return cls(options.address, timeout_s=options.move_timeout_s)

    @property
    def label(self) -> str:
        return label(self.name, self.host)

    @property
    def connected(self) -> bool:
        return self._control is not None and self._receive is not None

    # -- Robot Protocol -----------------------------------------------------------------

    def connect(self) -> None:
        if self.connected:
            return
        self._probe()
        try:
            import rtde_control
            import rtde_receive
        except ImportError as e:
            raise DeviceError(
                f"{self.label}: ur_rtde is not installed (pip install ur-rtde): {e}",
                device=ROBOT_NAME,
            ) from e
        host = self.host
        flags = rtde_control.RTDEControlInterface.FLAGS_DEFAULT

        def make() -> tuple[Any, Any]:
            receive = rtde_receive.RTDEReceiveInterface(host)
            try:
                control = rtde_control.RTDEControlInterface(host, flags=flags)
            except BaseException:
                try:
                    receive.disconnect()
                except _UR_ERRORS as e:
                    log.warning("%s: disconnect after a failed connect: %s", self.label, e)
                raise
            return receive, control

        self._receive, self._control = self._call(make, "connect")
        log.info("%s: connected", self.label)

    # move_joints is StopAndMeasureRobot's: the checks, then these three steps

    def _ready_to_move(self, target: Array) -> None:
        _, receive = self._require()
        self._check_safety(receive, f"cannot move to {_deg(target)}")

    def _move_and_settle(self, target: Array, speed: float) -> None:
        """``moveJ`` blocks until the move ended; a refused or aborted one is one line
        saying why (the receive connection may be a cycle behind: it is given SETTLE_S)."""
        control, receive = self._require()
        v = speed * self.velocity_rad_s
        a = self.acceleration_rad_s2
        qs = target.tolist()
        ok = self._call(lambda: control.moveJ(qs, v, a, False), "moveJ")
        if not ok:
            deadline = time.monotonic() + SETTLE_S
            while True:
                self._check_safety(receive, f"the move to {_deg(target)} did not complete")
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.01)
            running = self._quick(control.isProgramRunning, "isProgramRunning")
            why = (
                "the control script is not running (stopped on the pendant or by an error)"
                if not running
                else "the controller refused or aborted it"
            )
            raise DeviceError(
                f"{self.label}: moveJ to {_deg(target)} failed: {why}", device=ROBOT_NAME
            )
        self._check_safety(receive, f"the move to {_deg(target)} did not complete")

    def _check_arrived(self, target: Array) -> None:
        _, receive = self._require()
        err = self._position_error(receive, target)
        if err > POSITION_TOLERANCE_RAD:
            raise DeviceError(
                f"{self.label}: not in position after moveJ to {_deg(target)}: "
                f"a joint is {math.degrees(err):.4f} deg off (tolerance "
                f"{math.degrees(POSITION_TOLERANCE_RAD):.4f} deg)",
                device=ROBOT_NAME,
            )

    def actual_joints(self) -> Array:
        _, receive = self._require()
        return self._read6(receive.getActualQ, "getActualQ")

    def joint_temperatures(self) -> Array:
        """The joints' temperatures the controller reports (°C, one per joint)."""
        _, receive = self._require()
        return self._read6(receive.getJointTemperatures, "getJointTemperatures")

    def tcp_pose(self) -> Array:
        """The TCP pose in the base frame: [x, y, z (mm), rx, ry, rz (rad, rotation
        vector)] as one array of 6."""
        _, receive = self._require()
        pose = self._read6(receive.getActualTCPPose, "getActualTCPPose")
        pose[:3] *= 1000.0
        return pose

    def describe(self) -> DeviceDescription:
        """The controller at ``host``, as its dashboard server (29999) tells: robot model,
        serial number and PolyScope version (``PolyscopeVersion``: ``URSoftware
        5.11.1.108318 (Mar 22 2021)`` gives ``5.11.1.108318``); the maker from its welcome
        line. A dashboard that does not answer leaves them None (logged): a description
        never fails a campaign."""
        found: dict[str, str | None] = dict.fromkeys(("maker", *IDENTITY))
        try:
            found.update(dashboard_identity(self.host, min(self.timeout_s, 5.0)))
        except (OSError, ValueError) as e:
            log.warning("%s: no identity from the dashboard server: %s", self.label, _one_line(e))
        return DeviceDescription(
            ROBOT_NAME,
            "ur",
            self.host,
            maker=found["maker"],
            model=found["model"],
            firmware=found["firmware"],
            serial=found["serial"],
        )

    def stop(self) -> None:
        """Decelerate the joints to rest (stopJ); a no-op when not connected."""
        if not self.connected:
            return
        control = self._control
        a = max(self.acceleration_rad_s2, 2.0)
        self._call(lambda: control.stopJ(a, False), "stopJ", force=True)

    def close(self) -> None:
        """Stop the control script and disconnect; errors are logged, never raised."""
        held = {"control": self._control, "receive": self._receive}
        self._control = self._receive = None
        if held["control"] is None and held["receive"] is None:
            return

        def finish(key: str, methods: tuple[str, ...]) -> None:
            obj = held.pop(key)
            if obj is None:
                return
            for method in methods:
                try:
                    getattr(obj, method)()
                except Exception as e:
                    log.warning("%s: %s on close: %s", self.label, method, _one_line(e))
            # ur_rtde's destructor disconnects again (and sleeps 500 ms): let it happen
            # here, inside the time limit, rather than wherever the last reference goes.
            del obj

        def shutdown() -> None:
            # The two interfaces are independent and each disconnect sleeps 500 ms.
            other = threading.Thread(
                target=finish, args=("receive", ("disconnect",)), name=f"ur-{self.name}-close"
            )
            other.start()
            finish("control", ("stopScript", "disconnect"))
            other.join()

        try:
            self._call(shutdown, "close", force=True)
        except DeviceError as e:
            log.warning("%s", e)

    def __enter__(self) -> URRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers --------------------------------------------------------------------------

    def _probe(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        for port in PORTS:
            left = max(deadline - time.monotonic(), 0.1)
            try:
                with socket.create_connection((self.host, port), timeout=left):
                    pass  # connected: the port listens; nothing to send
            except OSError as e:
                reason = e.strerror or _one_line(e)
                raise DeviceError(
                    f"{self.label}: cannot reach port {port}: {reason}", device=ROBOT_NAME
                ) from e

    def _require(self) -> tuple[Any, Any]:
        if not self.connected:
            raise DeviceError(f"{self.label}: not connected", device=ROBOT_NAME)
        return self._control, self._receive

    def _check_safety(self, receive: Any, context: str) -> None:
        # ur_rtde 1.6.5 has isProtectiveStopped / isEmergencyStopped on the receive
        # interface only (the control interface checks the same bits inside its commands).
        if self._quick(receive.isEmergencyStopped, "isEmergencyStopped"):
            raise DeviceError(
                f"{self.label}: emergency stop; {context}. Release the emergency stop, "
                "power on and retry",
                device=ROBOT_NAME,
            )
        if self._quick(receive.isProtectiveStopped, "isProtectiveStopped"):
            raise DeviceError(
                f"{self.label}: protective stop; {context}. Inspect the cell, unlock the "
                "protective stop (pendant or dashboard) and retry",
                device=ROBOT_NAME,
            )

    def _position_error(self, receive: Any, target: Array) -> float:
        deadline = time.monotonic() + SETTLE_S
        while True:
            actual = self._read6(receive.getActualQ, "getActualQ")
            err = float(np.max(np.abs(actual - target)))
            if err <= POSITION_TOLERANCE_RAD or time.monotonic() >= deadline:
                return err
            time.sleep(0.01)

    def _read6(self, fn: Callable[[], Any], what: str) -> Array:
        values = np.asarray(self._call(fn, what), dtype=np.float64)
        if values.shape != (6,) or not np.all(np.isfinite(values)):
            raise DeviceError(
                f"{self.label}: {what} returned {values.tolist()!r}", device=ROBOT_NAME
            )
        return values

    def _quick(self, fn: Callable[[], T], what: str) -> T:
        """A call that does not wait for the robot: no worker thread."""
        try:
            return fn()
        except _UR_ERRORS as e:
            raise DeviceError(
                f"{self.label}: {what} failed: {_one_line(e)}", device=ROBOT_NAME
            ) from e

    def _call(self, fn: Callable[[], T], what: str, *, force: bool = False) -> T:
        """Run ``fn`` in a worker thread; give up after ``timeout_s``."""
        busy = self._worker
        if busy is not None and busy.is_alive():
            if not force:
                raise DeviceError(
                    f"{self.label}: {what} refused: an earlier command that timed out "
                    "has not returned yet",
                    device=ROBOT_NAME,
                )
        else:
            self._worker = None
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["value"] = fn()
            except BaseException as e:
                box["error"] = e

        worker = threading.Thread(target=run, name=f"ur-{self.name}-{what}", daemon=True)
        worker.start()
        worker.join(self.timeout_s)
        if worker.is_alive():
            self._worker = worker
            raise DeviceError(
                f"{self.label}: {what} timed out after {self.timeout_s:g} s", device=ROBOT_NAME
            )
        if "error" in box:
            e = box["error"]
            if isinstance(e, _UR_ERRORS):
                raise DeviceError(
                    f"{self.label}: {what} failed: {_one_line(e)}", device=ROBOT_NAME
                ) from e
            raise e
        value: T = box["value"]
        return value


def dashboard_identity(host: str, timeout_s: float) -> dict[str, str | None]:
    """Ask the dashboard server on ``host`` the questions of :data:`IDENTITY`, on one
    connection: what it answered (None where it did not understand), and ``maker``
    ("Universal Robots" when its welcome line says so). OSError when it does not answer
    within ``timeout_s`` a line; ValueError for a line longer than any answer."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
        reader = sock.makefile("rb")

        def line() -> str:
            raw = reader.readline(DASHBOARD_LINE + 1)
            if not raw:
                raise OSError("the dashboard server closed the connection")
            if len(raw) > DASHBOARD_LINE:
                raise ValueError(f"a dashboard line longer than {DASHBOARD_LINE} bytes")
            return raw.decode("utf-8", errors="replace").strip()

        welcome = line()
        out: dict[str, str | None] = {
            "maker": "Universal Robots" if "Universal Robots" in welcome else None
        }
        for key, question in IDENTITY.items():
            sock.sendall(f"{question}\n".encode("ascii"))
            answer = line()
            understood = answer and not answer.lower().startswith("could not understand")
            out[key] = answer if understood else None
        if out["firmware"] and out["firmware"].startswith("URSoftware "):
            out["firmware"] = out["firmware"].split()[1]
        return out
