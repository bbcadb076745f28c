"""The camera rig's twin: N GigE Vision cameras on 127.0.0.2.., drawing what a Python
frame source gives them, so that the real ``aravis`` driver runs unchanged against them.

Each camera is Aravis's own fake GigE Vision camera (``ArvGvFakeCamera``), which answers
GVCP and streams GVSP like a real one. It is driven through ctypes only: its fill-pattern
callback, given through PyGObject, crashes on the first frame. The callback runs on the
camera's thread each time a software trigger is accepted and asks
``source(camera_name)`` for the image of that instant (a numpy uint8/uint16 array,
height × width), or has ``writer(camera_name, buffer)`` write it straight into the
camera's buffer: the simulated cell renders its current pose there.

The cameras need their addresses on an interface and GVCP's port 3956 is fixed, so they
live in a private network namespace (:mod:`cellcal.mocks.netns`) made for a thread of
this process: only their threads are in it. The driver joins it by :attr:`netns` (the
``netns`` option of the rig): its camera threads enter the namespace, the rest of the
process stays in the host's network.

Adaptations of the fill: an image of another size than the camera's region is cropped or
padded with black; uint8 for Mono16 is scaled by 257, uint16 for Mono8 keeps its high
byte. A source that raises or gives no 2-D image makes a black frame (counted in
:meth:`errors`, logged once). The fake camera polls its trigger register
(``trigger_poll_hz``, every 3 ms here; Aravis's default of 25 Hz adds up to 40 ms a
frame). Its loop sleeps in ``poll()`` for whole milliseconds and spins (``poll()`` with
no timeout) through the last millisecond before each trigger poll: four idle cameras
kept a quarter to a third of a core busy at 200 Hz. So their threads get a timer slack
of :data:`TIMER_SLACK_NS` (1 ms: the kernel may end a sleep that much later), and the
last sleep runs into the trigger poll instead of spinning (four idle cameras: 3 % of a
core); a trigger received mid-wait is acted on up to 1 ms after its poll, and one
received, or a frame sent, within the last millisecond still spins to the poll.
Its frame ids start at 65401 and wrap after 65535 to 1, as Aravis does on purpose; its
timestamps are the host's wall clock in ns, or ``device_clock()`` (s) when given.

A fault of the fake camera (Aravis 0.8.26, ``arvgvfakecamera.c``), worked around here:
its loop computes its poll timeout as ``(next_timestamp_us - g_get_real_time ()) /
1000`` in unsigned arithmetic; when the time passes the deadline between the loop's
check and that line, the difference wraps, the timeout is capped at 100 ms, and a
trigger already received waits that long for its frame (one frame in 50–100 per
camera). Any control packet ends the wait. So a waker thread per twin (in the cameras'
namespace) watches each camera's software-trigger register and, when a trigger has been
pending for three trigger polls, sends the camera one GVCP register read.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Self

import numpy as np
from numpy.typing import NDArray

from cellcal.errors import DeviceError
from cellcal.mocks.netns import loopback_addresses, run_in_new_netns
from cellcal.mocks.twins import RunningTwin

if TYPE_CHECKING:
    from cellcal.drivers.cameras.aravis import AravisRigOptions

__all__ = ["PIXEL_FORMATS", "FrameSource", "FrameWriter", "GigECameraTwin", "serve_rig"]

log = logging.getLogger("cellcal.mocks.rig.gige_cameras")

FrameSource = Callable[[str], NDArray[Any]]
#: Writes camera ``name``'s frame of this instant into the given (height, width) array of
#: the stream's pixel type: the camera's own buffer, so no image is allocated per frame.
FrameWriter = Callable[[str, NDArray[Any]], None]

#: GenICam pixel format codes the twin serves.
PIXEL_FORMATS = {"Mono8": 0x01080001, "Mono16": 0x01100007}
_DTYPE: dict[int, np.dtype[Any]] = {0x01080001: np.dtype(np.uint8), 0x01100007: np.dtype(np.uint16)}

# ArvFakeCamera's registers (arvfakecamera.h, 0.8): host-order values.
_REG_WIDTH, _REG_HEIGHT = 0x100, 0x104
_REG_SENSOR_HEIGHT, _REG_SENSOR_WIDTH = 0x118, 0x11C
_REG_PIXEL_FORMAT = 0x128
_REG_TRIGGER_SOFTWARE = 0x30C
#: GVCP: a READREG command (key 0x42, no ack asked, command 0x0080, 4 bytes, id 1) of the
#: bootstrap Version register, to the fixed control port: it only wakes the camera.
_WAKE_PACKET = struct.pack(">BBHHHI", 0x42, 0x00, 0x0080, 4, 1, 0x0000)
_GVCP_PORT = 3956

#: The fake cameras' threads' timer slack, ns (the module's note).
TIMER_SLACK_NS = 1_000_000
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30
_libc = ctypes.CDLL(None, use_errno=True)
_libc.prctl.restype = ctypes.c_int
_libc.prctl.argtypes = [ctypes.c_int] + [ctypes.c_ulong] * 4

_vp, _u32 = ctypes.c_void_p, ctypes.c_uint32
#: void (*ArvFakeCameraFillPattern)(ArvBuffer *, void *data, guint32 exposure_us,
#: guint32 gain, ArvPixelFormat)
_FILL = ctypes.CFUNCTYPE(None, _vp, _vp, _u32, _u32, _u32)


class _Aravis:
    """The few libaravis calls the twin needs. Those that may wait release the GIL
    (CDLL); the getters and setters of a register or a buffer field, called at every
    frame and every trigger poll, keep it (PyDLL): they neither wait nor call back, and
    releasing the GIL only to take it again costs a handover between the cameras'
    threads each time."""

    def __init__(self) -> None:
        try:
            lib = ctypes.CDLL("libaravis-0.8.so.0")
            quick = ctypes.PyDLL("libaravis-0.8.so.0")
            gobject = ctypes.CDLL("libgobject-2.0.so.0")
        except OSError as exc:
            raise DeviceError(
                f"camera twin: {exc}; install it with `apt-get install libaravis-0.8-0`"
            ) from None

        def fn(lib: ctypes.CDLL | ctypes.PyDLL, name: str, restype: Any, *args: Any) -> Any:
            f = getattr(lib, name)
            f.restype, f.argtypes = restype, list(args)
            return f

        cp = ctypes.c_char_p
        self.gv_new = fn(lib, "arv_gv_fake_camera_new_full", _vp, cp, cp, cp)
        self.gv_running = fn(lib, "arv_gv_fake_camera_is_running", ctypes.c_int, _vp)
        self.gv_fake = fn(lib, "arv_gv_fake_camera_get_fake_camera", _vp, _vp)
        self.write = fn(lib, "arv_fake_camera_write_register", ctypes.c_int, _vp, _u32, _u32)
        self.read = fn(
            quick, "arv_fake_camera_read_register", ctypes.c_int, _vp, _u32, ctypes.POINTER(_u32)
        )
        self.trigger_hz = fn(
            lib, "arv_fake_camera_set_trigger_frequency", None, _vp, ctypes.c_double
        )
        self.set_fill = fn(lib, "arv_fake_camera_set_fill_pattern", None, _vp, _FILL, _vp)
        self.data = fn(quick, "arv_buffer_get_data", _vp, _vp, ctypes.POINTER(ctypes.c_size_t))
        self.width = fn(quick, "arv_buffer_get_image_width", ctypes.c_int, _vp)
        self.height = fn(quick, "arv_buffer_get_image_height", ctypes.c_int, _vp)
        self.set_timestamp = fn(quick, "arv_buffer_set_timestamp", None, _vp, ctypes.c_uint64)
        self.unref = fn(gobject, "g_object_unref", None, _vp)
        self.set_property = gobject.g_object_set  # variadic: (object, name, value, NULL)
        self.set_property.restype = None


def fit(image: NDArray[Any], height: int, width: int, dtype: np.dtype[Any]) -> NDArray[Any]:
    """``image`` as a C-contiguous (height, width) array of ``dtype``: cropped or padded
    with black, 8 ↔ 16 bits by scaling."""
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"frame source gave shape {a.shape}, not (height, width)")
    if a.dtype != dtype:
        if dtype == np.uint16 and a.dtype == np.uint8:
            a = a.astype(np.uint16) * 257
        elif dtype == np.uint8 and a.dtype == np.uint16:
            a = (a >> 8).astype(np.uint8)
        else:
            info = np.iinfo(dtype)
            a = np.clip(np.nan_to_num(a), info.min, info.max).astype(dtype)
    if a.shape != (height, width):
        out = np.zeros((height, width), dtype)
        h, w = min(height, a.shape[0]), min(width, a.shape[1])
        out[:h, :w] = a[:h, :w]
        a = out
    return np.ascontiguousarray(a)


@dataclass
class _Camera:
    name: str
    address: str
    gv: int | None = None
    fake: int | None = None
    callback: Any = None  # the CFUNCTYPE object: must outlive the camera
    frames: int = 0
    errors: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class GigECameraTwin:
    """Fake GigE Vision cameras ``names`` on 127.0.0.``first``.. in a private network
    namespace. ``start()`` brings them up (or raises :class:`~cellcal.errors.DeviceError`,
    :class:`~cellcal.mocks.netns.NamespaceUnavailableError` when no namespace can be
    made); ``addresses`` maps names to addresses, ``netns`` is the namespace's path for
    the driver; ``stop_camera(name)`` silences one camera and ``set_packet_loss(name,
    ratio)`` makes it drop packets (fault injection); ``stop()`` ends all."""

    def __init__(
        self,
        names: Sequence[str],
        source: FrameSource,
        *,
        width: int = 1280,
        height: int = 1024,
        pixel_format: str = "Mono8",
        trigger_poll_hz: float = 1000.0 / 3.0,
        device_clock: Callable[[], float] | None = None,
        first_address: int = 2,
        writer: FrameWriter | None = None,
    ) -> None:
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"camera twin: camera names must be distinct, got {list(names)}")
        if pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"camera twin: pixel format {pixel_format!r}: Mono8 or Mono16")
        if not (1 <= width <= 8192 and 1 <= height <= 8192):
            raise ValueError(f"camera twin: image size {width}×{height} out of 1..8192")
        addresses = loopback_addresses(len(names), first_address)
        self.cameras = {n: _Camera(n, a) for n, a in zip(names, addresses, strict=True)}
        self.source = source
        self.writer = writer
        self.width, self.height = width, height
        self.pixel_format = pixel_format
        self.trigger_poll_hz = trigger_poll_hz
        self.device_clock = device_clock
        self._lib: _Aravis | None = None
        self._ns_fd: int | None = None
        self._stopping = threading.Event()
        #: wake packets sent (see the module's note on the fake camera's stalls)
        self.wakes = 0

    @property
    def addresses(self) -> dict[str, str]:
        return {c.name: c.address for c in self.cameras.values()}

    @property
    def netns(self) -> str:
        """A path to the cameras' network namespace (valid until ``stop()``)."""
        if self._ns_fd is None:
            raise DeviceError("camera twin: not started")
        return f"/proc/{os.getpid()}/fd/{self._ns_fd}"

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Self:
        self._lib = _Aravis()
        addresses = [c.address for c in self.cameras.values()]
        _, self._ns_fd = run_in_new_netns(addresses, self._open_all)
        return self

    def _open_all(self) -> None:
        # the cameras' threads take this thread's timer slack (the module's note)
        slack = _timer_slack(TIMER_SLACK_NS)
        try:
            for c in self.cameras.values():
                self._open(c)
        except BaseException:
            self.stop()
            raise
        finally:
            _timer_slack(slack)
        # started here, it runs in the cameras' namespace
        threading.Thread(target=self._wake_stalled, name="camera-twin-waker", daemon=True).start()

    def _wake_stalled(self) -> None:
        """Send a camera a GVCP packet when its software trigger has waited three trigger
        polls (the fake camera's stall, see the module's note); until ``stop()``."""
        lib = self._lib
        assert lib is not None
        poll_s = 1.0 / self.trigger_poll_hz
        since: dict[str, float] = {}
        value = _u32()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            while not self._stopping.wait(poll_s):
                now = time.monotonic()
                for c in self.cameras.values():
                    with c.lock:  # stop_camera frees the camera under this lock
                        pending = (
                            c.fake is not None
                            and lib.read(c.fake, _REG_TRIGGER_SOFTWARE, ctypes.byref(value))
                            and value.value == 1
                        )
                    if not pending:
                        since.pop(c.name, None)
                    elif now - since.setdefault(c.name, now) > 3 * poll_s:
                        with contextlib.suppress(OSError):
                            sock.sendto(_WAKE_PACKET, (c.address, _GVCP_PORT))
                            self.wakes += 1
                        since[c.name] = now
                _drop_answers(sock)

    def _open(self, c: _Camera) -> None:
        lib = self._lib
        assert lib is not None
        gv = lib.gv_new(c.address.encode(), f"SIM-{c.name}".encode()[:15], None)
        if not gv:
            raise DeviceError(f"camera twin {c.name} at {c.address}: fake camera not created")
        c.gv = gv
        if not lib.gv_running(gv):
            raise DeviceError(f"camera twin {c.name} at {c.address}: address on no interface")
        fake = c.fake = lib.gv_fake(gv)
        for reg, value in (
            (_REG_SENSOR_WIDTH, self.width),
            (_REG_SENSOR_HEIGHT, self.height),
            (_REG_WIDTH, self.width),
            (_REG_HEIGHT, self.height),
            (_REG_PIXEL_FORMAT, PIXEL_FORMATS[self.pixel_format]),
        ):
            lib.write(fake, reg, value)
        lib.trigger_hz(fake, self.trigger_poll_hz)
        c.callback = _FILL(self._filler(c))
        lib.set_fill(fake, c.callback, None)

    def stop_camera(self, name: str) -> None:
        """Stop one camera: it answers nothing more (its thread is joined)."""
        c = self.cameras[name]
        with c.lock:
            gv, c.gv, c.fake = c.gv, None, None
        if gv is not None and self._lib is not None:
            self._lib.unref(gv)

    def set_packet_loss(self, name: str, ratio: float) -> None:
        """Make camera ``name`` drop this fraction of its stream packets (fault injection;
        the fake camera does not resend, so such frames come incomplete or not at all)."""
        c = self.cameras[name]
        if not 0.0 <= ratio <= 1.0:
            raise ValueError(f"packet loss ratio {ratio} outside 0..1")
        with c.lock:
            if c.gv is not None and self._lib is not None:
                self._lib.set_property(
                    _vp(c.gv), b"gvsp-lost-ratio", ctypes.c_double(ratio), _vp(None)
                )

    def stop(self) -> None:
        """Stop every camera and release the namespace; safe to call twice. The cameras
        stop one after the other: stopped from several threads at once, Aravis's fake
        cameras sometimes abort the process (SIGABRT, seen in the camera process's
        SIGINT test)."""
        self._stopping.set()
        for name in self.cameras:
            self.stop_camera(name)
        if self._ns_fd is not None:
            os.close(self._ns_fd)
            self._ns_fd = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def frames(self, name: str) -> int:
        """Frames served by camera ``name`` so far."""
        return self.cameras[name].frames

    def errors(self, name: str) -> int:
        """Frames of camera ``name`` drawn black because the source failed."""
        return self.cameras[name].errors

    # ------------------------------------------------------------------ the fill

    def _filler(self, c: _Camera) -> Callable[[int, int, int, int, int], None]:
        lib = self._lib
        assert lib is not None

        def fill(buffer: int, _data: int, _exposure_us: int, _gain: int, pixfmt: int) -> None:
            # On the fake camera's thread, ctypes holds the GIL; nothing may escape into C.
            try:
                dtype = _DTYPE.get(pixfmt)
                if dtype is None:
                    c.errors += 1
                    return
                h, w = lib.height(buffer), lib.width(buffer)
                data = lib.data(buffer, None)
                if self.writer is not None:
                    raw = (ctypes.c_uint8 * (h * w * dtype.itemsize)).from_address(data)
                    out = np.frombuffer(raw, dtype).reshape(h, w)
                    try:
                        self.writer(c.name, out)
                    except Exception as exc:
                        _source_failed(c, exc)
                        out[:] = 0
                else:
                    try:
                        image = fit(self.source(c.name), h, w, dtype)
                    except Exception as exc:
                        _source_failed(c, exc)
                        image = np.zeros((h, w), dtype)
                    ctypes.memmove(data, image.ctypes.data, image.nbytes)
                if self.device_clock is not None:
                    lib.set_timestamp(buffer, max(0, int(self.device_clock() * 1e9)))
                c.frames += 1
            except BaseException:  # never into C; the frame goes out as it is
                c.errors += 1

        return fill


def _timer_slack(ns: int) -> int:
    """Set this thread's timer slack (ns; the threads it starts inherit it) and return
    the one it had; where the kernel does not tell (-1), nothing is set."""
    previous = int(_libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))
    if previous > 0 and ns > 0:
        _libc.prctl(_PR_SET_TIMERSLACK, ns, 0, 0, 0)
    return previous


def _drop_answers(sock: socket.socket) -> None:
    """Read and drop what the cameras answered to the wake packets."""
    with contextlib.suppress(OSError):  # BlockingIOError: nothing (more) to read
        while sock.recv(576):
            continue


def _source_failed(c: _Camera, exc: Exception) -> None:
    """A frame the source could not give goes out black: counted, logged once."""
    if c.errors == 0:
        log.warning("camera twin %s: frame source failed: %s", c.name, exc)
    c.errors += 1


def serve_rig(
    options: AravisRigOptions,
    source: FrameSource,
    *,
    width: int = 1280,
    height: int = 1024,
    device_clock: Callable[[], float] | None = None,
    writer: FrameWriter | None = None,
) -> RunningTwin:
    """Start a twin of the configured rig (its cameras by name, sensors ``width`` ×
    ``height``, the first camera's pixel format) and return it with the options pointed
    at it: each camera's address is its twin's, ``netns`` the twin's namespace. With a
    ``writer`` the frames are written into the cameras' buffers (``source`` unused)."""
    names = [c.name for c in options.cameras]
    twin = GigECameraTwin(
        names,
        source,
        width=width,
        height=height,
        pixel_format=options.cameras[0].pixel_format,
        device_clock=device_clock,
        writer=writer,
    ).start()
    cameras = [c.model_copy(update={"address": twin.addresses[c.name]}) for c in options.cameras]
    pointed = options.model_copy(update={"cameras": cameras, "netns": twin.netns})
    return RunningTwin(pointed, twin)
