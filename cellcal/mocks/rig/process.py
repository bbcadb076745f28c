"""The rig's GigE Vision twin in a process of its own.

Rendering the target and filling the cameras' frames is Python and numpy work; in the
campaign's process it would take turns under one interpreter lock with the driver
measuring those frames, as a real rig's cameras do not. So mock mode starts the twin in
a child process (``spawn``: the campaign's threads are not forked):

* the child gets the rig's truth (:class:`~cellcal.mocks.rig.twin.RigTruth`) and the
  sensor's options, reads the rig and target files itself, makes its network namespace
  and serves the cameras there (:func:`~cellcal.mocks.rig.twin.serve_gige`);
* it follows the simulated robot through six shared doubles the campaign's process
  writes at every move (:meth:`~cellcal.mocks.simulated_cell.SimulatedCell.watch`),
  and the rig's sets through four more, which the sensor's set listener
  (:meth:`CameraProcess.announce`) writes before each set is triggered
  (:class:`~cellcal.mocks.rig.twin.SetMark`: each frame's noise and timestamp);
* it answers with the options that point the ``aravis`` driver at its cameras (the
  namespace as ``/proc/<child>/fd/<n>``), or with the reason it could not;
* it serves until told to stop, or until the campaign's process is gone (its end of the
  pipe closes): a killed campaign leaves no camera behind. Tests may have it stop one
  camera (fault injection);
* it ignores SIGINT: a Ctrl-C on a terminal goes to the whole foreground process group,
  the child included, and the child is the campaign's to stop (after the pose under way,
  which it serves to the end). SIGINT is blocked in the starting thread while the child
  starts, so the child inherits it blocked and sets it ignored before anything else can
  take it: no ``KeyboardInterrupt`` at any moment of its life.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import sys
import traceback
from collections.abc import Iterator
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.calib.geometry import Array
from cellcal.drivers.photogrammetry import CameraRigOptions, rig_and_target
from cellcal.errors import DeviceError
from cellcal.mocks.netns import NamespaceUnavailableError
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.twins import RunningTwin

if TYPE_CHECKING:
    from cellcal.mocks.rig.twin import RigTruth, SetMark

log = logging.getLogger("cellcal.mocks.rig")

#: How long the child may take to import, render its noise bank and open its cameras, s.
START_S = 60.0
#: How long it may take to stop, s, before it is terminated.
STOP_S = 10.0


class _Joints:
    """The robot's joint angles (rad) shared between the two processes."""

    def __init__(self, shared: Any) -> None:
        self.shared = shared

    def write(self, q: Array) -> None:
        with self.shared.get_lock():
            self.shared[:] = [float(v) for v in q]

    def read(self) -> Array:
        with self.shared.get_lock():
            return np.array(self.shared[:], dtype=np.float64)


class _Marks:
    """The last set announced (:class:`~cellcal.mocks.rig.twin.SetMark`), shared between
    the two processes as four doubles; a pose of -1 before any."""

    def __init__(self, shared: Any) -> None:
        self.shared = shared

    def write(self, pose: int, visit: int, index: int, t: float) -> None:
        with self.shared.get_lock():
            self.shared[:] = [float(pose), float(visit), float(index), t]

    def read(self) -> SetMark | None:
        from cellcal.mocks.rig.twin import SetMark

        with self.shared.get_lock():
            pose, visit, index, t = self.shared[:]
        return None if pose < 0 else SetMark(int(pose), int(visit), int(index), t)


class CameraProcess:
    """The running child: ``announce(index, t)`` tells it the set the sensor triggers
    next (where the simulated robot is now); ``stop()`` ends it (and stops following
    the robot)."""

    def __init__(
        self,
        process: BaseProcess,
        pipe: Connection,
        unwatch: Any,
        marks: _Marks,
        cell: SimulatedCell,
    ) -> None:
        self.process = process
        self.pipe = pipe
        self.unwatch = unwatch
        self.marks = marks
        self.cell = cell

    def announce(self, index: int, t: float) -> None:
        pose, visit = self.cell.pose_key
        self.marks.write(pose, visit, index, t)

    def stop_camera(self, name: str) -> None:
        """Fault injection: camera ``name`` answers nothing more (as in
        :meth:`~cellcal.mocks.rig.gige_cameras.GigECameraTwin.stop_camera`)."""
        self.pipe.send(("stop_camera", name))
        if not self.pipe.poll(STOP_S) or self.pipe.recv() != "done":
            raise DeviceError(f"camera twin: camera {name} did not stop")

    def stop(self) -> None:
        self.unwatch()
        with contextlib.suppress(OSError, ValueError):  # the child may be gone already
            self.pipe.send("stop")
        self.process.join(STOP_S)
        if self.process.is_alive():
            log.warning("camera twin: did not stop within %g s; terminated", STOP_S)
            self.process.terminate()
            self.process.join(STOP_S)
        self.pipe.close()


def serve_in_process(
    options: CameraRigOptions, truth: RigTruth, cell: SimulatedCell
) -> RunningTwin:
    """Start the rig's twin in a child process; its options point the driver at it.
    Raises :class:`NamespaceUnavailableError` when the child cannot make its namespace,
    :class:`DeviceError` when it fails otherwise."""
    ctx = multiprocessing.get_context("spawn")
    joints = _Joints(ctx.Array("d", len(cell.q)))
    marks = _Marks(ctx.Array("d", [-1.0, 0.0, 0.0, 0.0]))
    unwatch = cell.watch(joints.write)
    ours, theirs = ctx.Pipe()
    process = ctx.Process(
        target=_child_main,
        args=(options, truth, joints.shared, marks.shared, theirs),
        name=f"{options.name}-cameras",
        daemon=True,
    )
    try:
        with _interrupt_blocked():
            process.start()
    except OSError as exc:
        unwatch()
        raise DeviceError(f"camera twin: cannot start its process ({exc})") from None
    theirs.close()
    child = CameraProcess(process, ours, unwatch, marks, cell)
    try:
        if not ours.poll(START_S):
            raise DeviceError(f"camera twin: its process did not start within {START_S:g} s")
        kind, payload = ours.recv()
    except EOFError:
        child.stop()
        raise DeviceError(
            f"camera twin: its process ended on start (exit code {process.exitcode})"
        ) from None
    except BaseException:
        child.stop()
        raise
    if kind != "ok":
        child.stop()
        if kind == "unavailable":
            raise NamespaceUnavailableError(payload)
        raise DeviceError(f"camera twin: {payload}")
    return RunningTwin(payload, child)


@contextlib.contextmanager
def _interrupt_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread while a child starts: the child inherits the mask
    and unblocks it once it ignores SIGINT (:func:`_ignore_interrupts`). A SIGINT meant
    for this process is not lost meanwhile: another thread takes it, or it waits here
    until the mask is restored."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _ignore_interrupts() -> None:
    """The child: SIGINT ignored (one pending since its start is dropped), then unblocked."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _child_main(
    options: CameraRigOptions, truth: RigTruth, shared: Any, marked: Any, pipe: Connection
) -> None:
    """The child: serve the rig's cameras until told to stop or orphaned; a Ctrl-C on
    the terminal is its parent's to act on. Once it has stopped its cameras and said what
    it has to say it leaves at once (``os._exit``): the interpreter's own exit runs the
    native libraries' destructors while OpenCV's worker threads may still be alive, and
    that aborted the process now and then ("terminate called without an active
    exception", SIGABRT, on a loaded machine)."""
    _ignore_interrupts()
    code = 0
    try:
        _serve(options, truth, shared, marked, pipe)
    except BaseException:  # what went wrong is said, as the interpreter would say it
        traceback.print_exc()
        code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


def _serve(
    options: CameraRigOptions, truth: RigTruth, shared: Any, marked: Any, pipe: Connection
) -> None:
    """Open the cameras, say so (or why not) on the pipe, serve until told to stop."""
    from cellcal.families import camera_backend, load
    from cellcal.mocks.rig.gige_cameras import GigECameraTwin
    from cellcal.mocks.rig.twin import RigScene

    joints, marks = _Joints(shared), _Marks(marked)
    try:
        rig, target = rig_and_target(options)
        scene = RigScene(truth, rig, target, joints.read, mark=marks.read)
        row = camera_backend(options.capture.backend)
        assert row is not None and row.twin is not None  # serve() chose it for its twin
        running = load(row.twin)(options, scene)
    except NamespaceUnavailableError as exc:
        pipe.send(("unavailable", str(exc)))
        return
    except Exception as exc:  # the parent reports it in one line
        pipe.send(("error", str(exc) or type(exc).__name__))
        return
    # serve until "stop", or until EOFError / OSError: the campaign's process is gone
    try:
        with contextlib.suppress(EOFError, OSError):
            pipe.send(("ok", running.options))
            while (message := pipe.recv()) != "stop":
                if isinstance(message, tuple) and message[0] == "stop_camera":
                    assert isinstance(running.server, GigECameraTwin)
                    running.server.stop_camera(message[1])
                    pipe.send("done")
    finally:
        running.stop()
