"""The ``aravis`` camera rig: GigE Vision (and USB3 Vision) cameras of any vendor through
Aravis 0.8 (PyGObject), each opened by its address, never by discovery.

Each camera gets a thread of its own that makes all of its Aravis calls: it opens the
camera, sets software trigger, exposure (µs), gain, pixel format (Mono8/Mono16), the
region (the full sensor unless configured) and, on GigE Vision, a fixed packet size
(``GevSCPSPacketSize``, no negotiation), and keeps a stream with a few buffers. A set
(:meth:`AravisRig.grab`) asks every thread at once to trigger its camera and pop the
frame; a frame that is not complete (buffer status other than SUCCESS) or does not come
within ``timeout_s`` is grabbed again, up to ``retries`` times, then the camera is named
in the set's ``lost`` with the reason.

Aravis waits 2.5 s (hard-coded) for a camera's answer to any control command. The rig
does not: it waits at most ``timeout_s × (retries + 1)`` for the slowest camera, and a
camera whose thread is still waiting (a camera gone mid-series) is reported lost; until
its thread is free again the camera is reported lost at once. A trigger that Aravis
could not get acknowledged in its 2.5 s is not sent again: a camera that no longer
answers on its control channel has dropped it (a GigE Vision camera gives up control
when its heartbeat stops), so it is reported lost at once in every later set, until
the rig connects again.

Frame ids: GigE Vision 1.x counts frames in 16 bits, wrapping from 65535 to 1; the rig
unwraps them into a count that keeps increasing. Device time is the camera's timestamp
(s); host time is the context clock at the frame's arrival (s).

With ``netns`` (a path to a network namespace, e.g. the camera twin's or one made by
``ip netns add``), the camera threads enter that namespace before opening their
cameras: the rest of the process stays in its own network.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import Future, wait
from typing import Annotated, Any, Literal

from pydantic import Field

from cellcal.clock import Clock, WallClock
from cellcal.drivers.base import DeviceDescription, label
from cellcal.drivers.cameras.aravis_link import AravisLink, Shot, load_aravis
from cellcal.drivers.cameras.backends import CameraOptions, Frame, FrameSet, RigOptions
from cellcal.errors import DeviceError

__all__ = ["AravisCameraOptions", "AravisRig", "AravisRigOptions", "aravis_missing"]

CLONE_NEWNET = 0x40000000
#: how long ``connect`` waits for every camera to open and be configured
CONNECT_S = 10.0
#: how long ``close`` waits for the cameras to stop acquiring
CLOSE_S = 3.0


class AravisCameraOptions(CameraOptions):
    """One GigE Vision / USB3 Vision camera: ``address`` its IP (or Aravis device id);
    exposure (µs), gain (the camera's unit), pixel format, GigE packet size (bytes, no
    negotiation: 1500-byte links need ≤ 1400, jumbo frames 8000), region (x, y, width,
    height px; the full sensor when not given)."""

    address: Annotated[str, Field(min_length=1)]
    exposure_us: Annotated[float, Field(gt=0, le=10_000_000)] = 10_000.0
    gain: Annotated[float, Field(ge=0)] = 0.0
    pixel_format: Literal["Mono8", "Mono16"] = "Mono8"
    packet_size: Annotated[int, Field(ge=576, le=16404)] = 8000
    region: Annotated[list[int], Field(min_length=4, max_length=4)] | None = None
    buffers: Annotated[int, Field(ge=2, le=64)] = 4
    #: how a GigE Vision stream is received: ``udp``, a UDP socket with a receive buffer
    #: of two frames; ``packet``, Aravis's raw packet socket (with CAP_NET_RAW); ``auto``,
    #: ``udp`` where net.core.rmem_max allows two frames, else Aravis's own choice
    stream_socket: Literal["auto", "udp", "packet"] = "auto"


class AravisRigOptions(RigOptions):
    """A rig with ``backend = "aravis"``: its cameras and, optionally, the network
    namespace they are reached in."""

    backend: Literal["aravis"] = "aravis"
    cameras: Annotated[list[AravisCameraOptions], Field(min_length=1)]
    netns: str = ""


def aravis_missing() -> str | None:
    """Why the aravis backend cannot run here (one line), or None when it can."""
    try:
        load_aravis()
    except DeviceError as exc:
        return str(exc)
    return None


_libc = ctypes.CDLL(None, use_errno=True)


def _enter_netns(path: str) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        if _libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise DeviceError(f"cannot enter network namespace {path}: {os.strerror(err)}")
    finally:
        os.close(fd)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


class _Worker:
    """One thread that runs one camera's calls in order (in ``netns`` if given)."""

    def __init__(self, name: str, where: str, netns: str) -> None:
        self._where = where
        self._jobs: list[tuple[Any, Future[Any]] | None] = []
        self._ready = threading.Condition()
        self._netns = netns
        self._pending: Future[Any] | None = None
        self._thread = threading.Thread(target=self._run, name=f"camera-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        failure: BaseException | None = None
        if self._netns:
            try:
                _enter_netns(self._netns)
            except (DeviceError, OSError) as exc:
                failure = DeviceError(f"{self._where}: {_one_line(exc)}")
        while True:
            with self._ready:
                while not self._jobs:
                    self._ready.wait()
                job = self._jobs.pop(0)
            if job is None:
                return
            fn, future = job
            if not future.set_running_or_notify_cancel():
                continue
            if failure is not None:
                future.set_exception(failure)
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:
                future.set_exception(exc)

    @property
    def busy(self) -> bool:
        return self._pending is not None and not self._pending.done()

    def submit(self, fn: Any) -> Future[Any]:
        future: Future[Any] = Future()
        with self._ready:
            self._jobs.append((fn, future))
            self._ready.notify()
        self._pending = future
        return future

    def stop(self) -> None:
        """End the thread after the jobs already given (it is a daemon: never waited for)."""
        with self._ready:
            self._jobs.append(None)
            self._ready.notify()


class AravisRig:
    """Cameras through Aravis, behind the :class:`~cellcal.drivers.cameras.backends.CameraRig`
    Protocol."""

    def __init__(self, options: AravisRigOptions, *, clock: Clock | None = None) -> None:
        self.name = options.name
        self.options = options
        self.cameras = tuple(c.name for c in options.cameras)
        self.clock = clock or WallClock()
        self._links: dict[str, AravisLink] = {}
        self._workers: dict[str, _Worker] = {}
        self._lost: set[str] = set()  # cameras lost in the last set

    @classmethod
    def from_options(cls, options: AravisRigOptions, clock: Clock | None = None) -> AravisRig:
        return cls(options, clock=clock)

    @property
    def deadline_s(self) -> float:
        """The longest a set may take: the slowest camera's attempts."""
        return max(c.timeout_s * (c.retries + 1) for c in self.options.cameras)

    def connect(self) -> None:
        """Open and configure every camera at once; one DeviceError line naming each
        camera that failed."""
        load_aravis()
        self.close()
        opening: dict[str, Future[None]] = {}
        for cam in self.options.cameras:
            link = AravisLink(cam, self.clock)
            worker = _Worker(cam.name, link.where, self.options.netns)
            self._links[cam.name], self._workers[cam.name] = link, worker
            opening[cam.name] = worker.submit(link.open)
        wait(opening.values(), timeout=CONNECT_S)
        self._raise_failures(opening)
        for cam in self.options.cameras:  # one at a time: see AravisLink.start
            starting = {cam.name: self._workers[cam.name].submit(self._links[cam.name].start)}
            wait(starting.values(), timeout=CONNECT_S)
            self._raise_failures(starting)
        if any(link.udp for link in self._links.values()):
            # Aravis sizes a UDP socket's buffer as a frame begins: this set's frames may
            # come incomplete (and be retried), the next ones have the whole buffer.
            self.grab()

    def _raise_failures(self, futures: dict[str, Future[None]]) -> None:
        errors = []
        for cam in self.options.cameras:
            future = futures.get(cam.name)
            if future is None:
                continue
            if not future.done():
                where = label(f"camera {cam.name}", cam.address)
                errors.append(f"{where}: no answer within {CONNECT_S:g} s")
            elif (exc := future.exception()) is not None:
                errors.append(_one_line(exc))
        if errors:
            self.close()
            raise DeviceError("; ".join(errors))

    def grab(self) -> FrameSet:
        if not self._links:
            raise DeviceError(f"rig {self.name}: not connected")
        pending: dict[str, Future[Shot]] = {}
        lost: dict[str, str] = {}
        for name in self.cameras:
            worker = self._workers[name]
            if self._links[name].gone:
                lost[name] = "not answering: a trigger went unacknowledged"
            elif worker.busy:
                lost[name] = "still waiting for its previous command (camera gone?)"
            else:
                pending[name] = worker.submit(self._links[name].shot)
        wait(pending.values(), timeout=self.deadline_s + 0.05)
        frames: dict[str, Frame] = {}
        for name, future in pending.items():
            if not future.done():
                lost[name] = f"no frame within {self.deadline_s:g} s (the camera does not answer)"
            elif (exc := future.exception()) is not None:
                lost[name] = _one_line(exc)
            else:
                shot = future.result()
                if shot.frame is not None:
                    frames[name] = shot.frame
                else:
                    lost[name] = shot.reason
        self._lost = set(lost)
        return FrameSet(frames=frames, lost={n: lost[n] for n in self.cameras if n in lost})

    def describe(self) -> tuple[DeviceDescription, ...]:
        """Each camera as it says of itself (:meth:`AravisLink.identity`, asked on its
        thread, at most ``CONNECT_S`` in all); a camera not connected, lost, busy or
        silent is its name and address only."""
        asked: dict[str, Future[DeviceDescription]] = {}
        for name, link in self._links.items():
            if not link.gone and not self._workers[name].busy:
                asked[name] = self._workers[name].submit(link.identity)
        wait(asked.values(), timeout=CONNECT_S)
        out = []
        for cam in self.options.cameras:
            future = asked.get(cam.name)
            if future is not None and future.done() and future.exception() is None:
                out.append(future.result())
            else:
                out.append(DeviceDescription(cam.name, "aravis", cam.address))
        return tuple(out)

    def close(self) -> None:
        """Stop acquisition and release every camera; safe to call twice. Waits up to
        ``CLOSE_S`` for the cameras that answered last; one that was lost is released by
        its thread in the background (Aravis may wait 2.5 s per command on it)."""
        closing = []
        for name, link in self._links.items():
            future = self._workers[name].submit(link.close)
            if name not in self._lost:
                closing.append(future)
            self._workers[name].stop()
        wait(closing, timeout=CLOSE_S)
        self._links.clear()
        self._workers.clear()
        self._lost.clear()

    def __enter__(self) -> AravisRig:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
