"""One Aravis camera of the ``aravis`` rig: open and configure it, grab one frame with
retries, release it. Every call of an :class:`AravisLink` is made on its camera's own
thread (``camera_aravis``), so nothing here locks."""

from __future__ import annotations

import ctypes
import logging
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.clock import Clock
from cellcal.drivers.base import DeviceDescription, label
from cellcal.drivers.cameras.backends import Frame
from cellcal.errors import DeviceError

if TYPE_CHECKING:
    from cellcal.drivers.cameras.aravis import AravisCameraOptions

log = logging.getLogger("cellcal.cameras.aravis")

INSTALL = (
    "install it with `apt-get install libaravis-0.8-0 gir1.2-aravis-0.8 "
    "libgirepository1.0-dev libcairo2-dev pkg-config` then `pip install 'PyGObject<3.51'` "
    "(`make unit` does both as root)"
)
_DTYPE: dict[str, np.dtype[Any]] = {"Mono8": np.dtype(np.uint8), "Mono16": np.dtype(np.uint16)}


@dataclass(frozen=True)
class _Aravis:
    Aravis: Any
    GLib: Any
    buffer_data: Any  # const void *arv_buffer_get_data(ArvBuffer *, size_t *size)


_loaded: list[_Aravis] = []


def load_aravis() -> _Aravis:
    """PyGObject's Aravis 0.8 (imported once), or a DeviceError line saying what to install."""
    if not _loaded:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis, GLib

            lib = ctypes.CDLL("libaravis-0.8.so.0")
        except (ImportError, ValueError, OSError) as exc:
            raise DeviceError(f"aravis backend unavailable ({exc}): {INSTALL}") from None
        buffer_data = lib.arv_buffer_get_data
        buffer_data.restype = ctypes.c_void_p
        buffer_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        _loaded.append(_Aravis(Aravis, GLib, buffer_data))
    return _loaded[0]


def rmem_max() -> int:
    """net.core.rmem_max (bytes): the most a UDP socket's receive buffer may be set to
    without CAP_NET_ADMIN; 0 where it cannot be read."""
    try:
        with open("/proc/sys/net/core/rmem_max", encoding="ascii") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return 0


_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype = ctypes.c_void_p
_capsule_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]


def _text(exc: BaseException) -> str:
    """A GLib.Error (or any error) as one line."""
    return " ".join(str(getattr(exc, "message", None) or exc).split())


@dataclass(frozen=True)
class Shot:
    """What one camera gave for a set: its frame, or why it gave none."""

    frame: Frame | None
    reason: str = ""


class AravisLink:
    """One camera: ``open()``, ``start()``, ``shot()`` as often as needed, ``close()``."""

    def __init__(self, options: AravisCameraOptions, clock: Clock) -> None:
        self.options = options
        self.clock = clock
        self.where = label(f"camera {options.name}", options.address)
        self.dtype = _DTYPE[options.pixel_format]
        self.cam: Any = None
        self.stream: Any = None
        self._last_id: int | None = None
        #: the camera stopped answering commands: its trigger went unacknowledged (it is not
        #: triggered again, and its stop would wait for Aravis's timeout)
        self.gone = False
        #: the stream comes through a UDP socket whose buffer Aravis sizes at a frame
        self.udp = False
        self._count = 0

    def _error(self, what: str) -> DeviceError:
        return DeviceError(f"{self.where}: {' '.join(what.split())}")

    # ------------------------------------------------------------------ open, close

    def open(self) -> None:
        a = load_aravis()
        try:
            self.cam = a.Aravis.Camera.new(self.options.address)  # by address: no discovery
        except a.GLib.Error as exc:
            raise self._error(f"cannot open ({_text(exc)})") from None
        if self.cam is None:
            raise self._error("cannot open (no such device)")
        try:
            self._configure(a.Aravis)
        except a.GLib.Error as exc:
            self.close()
            raise self._error(f"cannot configure ({_text(exc)})") from None
        except DeviceError:
            self.close()
            raise

    def _configure(self, Aravis: Any) -> None:
        o, cam = self.options, self.cam
        cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
        cam.set_pixel_format_from_string(o.pixel_format)
        sensor_w, sensor_h = cam.get_sensor_size()
        x, y, w, h = o.region or (0, 0, sensor_w, sensor_h)
        if x < 0 or y < 0 or w < 1 or h < 1 or x + w > sensor_w or y + h > sensor_h:
            raise self._error(f"region {x},{y},{w},{h} outside the {sensor_w}×{sensor_h} sensor")
        cam.set_region(x, y, w, h)
        if tuple(cam.get_region()) != (x, y, w, h):
            raise self._error(f"region {x},{y},{w},{h} refused (camera has {cam.get_region()})")
        for feature, value in (
            ("TriggerSelector", "FrameStart"),
            ("TriggerMode", "On"),
            ("TriggerSource", "Software"),
        ):
            cam.set_string(feature, value)
        if cam.is_exposure_auto_available():
            cam.set_exposure_time_auto(Aravis.Auto.OFF)
        lo, hi = cam.get_exposure_time_bounds()
        if not lo <= o.exposure_us <= hi:
            raise self._error(f"exposure {o.exposure_us:g} µs outside {lo:g}..{hi:g} µs")
        cam.set_exposure_time(o.exposure_us)
        if cam.is_gain_auto_available():
            cam.set_gain_auto(Aravis.Auto.OFF)
        lo, hi = cam.get_gain_bounds()
        if not lo <= o.gain <= hi:
            raise self._error(f"gain {o.gain:g} outside {lo:g}..{hi:g}")
        cam.set_gain(o.gain)
        if cam.is_gv_device():
            cam.gv_set_packet_size_adjustment(Aravis.GvPacketSizeAdjustment.NEVER)
            cam.gv_set_packet_size(o.packet_size)

    def start(self) -> None:
        """Create the stream with its buffers and start acquiring.

        A GigE Vision stream comes either through a UDP socket, whose receive buffer is
        capped by net.core.rmem_max, or, with CAP_NET_RAW (root), through Aravis's raw
        packet socket (a 32 MB ring of blocks the kernel hands over when full or after
        5 ms: a frame can wait there 100 ms and more for its last block). ``udp`` asks
        for a buffer of two frames (Aravis sizes it when a frame begins, so one frame is
        grabbed and dropped here to size it before any set); ``auto`` takes ``udp``
        where rmem_max allows that, else leaves the choice to Aravis. The packet socket
        takes in whatever the interface carries until its filter is set; so the rig
        starts its cameras one at a time, and the stray packets come out as unfilled
        buffers that ``shot`` skips."""
        a = load_aravis()
        try:
            payload = self.cam.get_payload()
            buffer = self._udp_buffer(payload) if self.cam.is_gv_device() else None
            udp = self.udp = buffer is not None
            if udp:
                self.cam.get_device().set_stream_options(
                    a.Aravis.GvStreamOption.PACKET_SOCKET_DISABLED
                )
            self.stream = self.cam.create_stream(None, None)
            if self.stream is None:
                raise self._error("no stream")
            if udp:
                self.stream.set_property("socket-buffer", a.Aravis.GvStreamSocketBuffer.FIXED)
                self.stream.set_property("socket-buffer-size", buffer)
            for _ in range(self.options.buffers):
                self.stream.push_buffer(a.Aravis.Buffer.new_allocate(payload))
            self.cam.start_acquisition()
        except a.GLib.Error as exc:
            self.close()
            raise self._error(f"cannot start acquisition ({_text(exc)})") from None

    def _udp_buffer(self, payload: int) -> int | None:
        """The UDP receive buffer to ask for (bytes): two frames; None for Aravis's
        choice (``packet``, or ``auto`` where net.core.rmem_max is below two frames)."""
        mode = self.options.stream_socket
        want = 2 * int(payload)
        if mode == "packet" or (mode == "auto" and rmem_max() < want):
            return None
        return want

    def close(self) -> None:
        """Stop acquisition and drop the camera (which releases its control); safe twice."""
        if self.cam is not None and not self.gone:
            try:
                self.cam.stop_acquisition()
            except load_aravis().GLib.Error as exc:
                log.info("%s: stop_acquisition: %s", self.where, _text(exc))
        self.stream = None
        self.cam = None

    def identity(self) -> DeviceDescription:
        """The camera as it says of itself (GenICam's DeviceVendorName, DeviceModelName,
        serial number, DeviceFirmwareVersion — else GigE Vision's device version, which
        cameras fill with their firmware's): what it does not say stays None, as does
        all of it for a camera not open."""
        described = DeviceDescription(self.options.name, "aravis", self.options.address)
        cam = self.cam
        if cam is None:
            return described
        a = load_aravis()

        def said(ask: Any, *args: str) -> str | None:
            try:
                value = ask(*args)
            except a.GLib.Error:
                return None
            text = "" if value is None else str(value).strip()
            return text or None

        return replace(
            described,
            maker=said(cam.get_vendor_name),
            model=said(cam.get_model_name),
            firmware=said(cam.get_string, "DeviceFirmwareVersion")
            or said(cam.get_string, "DeviceVersion"),
            # Aravis before 0.8.8 has no serial number getter: DeviceID, SFNC's older name
            serial=said(getattr(cam, "get_device_serial_number", cam.get_device_id)),
        )

    # ------------------------------------------------------------------ frames

    def shot(self) -> Shot:
        """Trigger the camera and take its frame; incomplete or late frames are grabbed
        again, up to ``retries`` times, within ``timeout_s × (retries + 1)``. A trigger
        that is not acknowledged ends the attempts and marks the camera ``gone``."""
        if self.cam is None or self.stream is None:
            return Shot(None, "not open")
        a = load_aravis()
        o = self.options
        deadline = time.monotonic() + o.timeout_s * (o.retries + 1)
        reason = "no time left"
        attempts = 0
        for attempt in range(o.retries + 1):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            attempts += 1
            self._drain()
            try:
                self.cam.software_trigger()
            except a.GLib.Error as exc:
                # Aravis has sent the command again for 2.5 s: the camera no longer
                # answers on its control channel (a GigE Vision camera then gives up
                # control too), and triggering it again would give nothing
                reason = f"trigger not acknowledged ({_text(exc)})"
                self.gone = True
                break
            wait_s = max(0.001, min(o.timeout_s, deadline - time.monotonic()))
            buf = self._pop(a, time.monotonic() + wait_s)
            if buf is None:
                reason = f"no frame within {wait_s:.3g} s"
                continue
            try:
                status = buf.get_status()
                if status != a.Aravis.BufferStatus.SUCCESS:
                    reason = f"incomplete frame (buffer status {status.value_nick})"
                    continue
                return Shot(self._frame(a, buf, attempt))
            finally:
                self.stream.push_buffer(buf)
        log.warning("%s: lost after %d attempts: %s", self.where, attempts, reason)
        return Shot(None, f"no frame after {attempts} attempt(s): {reason}")

    def _pop(self, a: _Aravis, until: float) -> Any:
        """The next buffer the stream filled, or None at ``until`` (monotonic s). Buffers
        handed back unfilled (status CLEARED: a packet that began no image) are not
        frames: they go back to the stream and the wait goes on."""
        while (left := until - time.monotonic()) > 0:
            buf = self.stream.timeout_pop_buffer(max(1, int(left * 1e6)))
            if buf is None or buf.get_status() != a.Aravis.BufferStatus.CLEARED:
                return buf
            self.stream.push_buffer(buf)
        return None

    def _drain(self) -> None:
        """Give back frames that came too late for an earlier set."""
        while (old := self.stream.try_pop_buffer()) is not None:
            self.stream.push_buffer(old)

    def _frame(self, a: _Aravis, buf: Any, retries: int) -> Frame:
        h, w = buf.get_image_height(), buf.get_image_width()
        n = h * w * self.dtype.itemsize
        size = ctypes.c_size_t()
        data = a.buffer_data(_capsule_pointer(buf.__gpointer__, None), ctypes.byref(size))
        if not data or size.value < n:
            fmt = self.options.pixel_format
            raise self._error(f"frame of {size.value} bytes for {w}×{h} {fmt}")
        raw = (ctypes.c_uint8 * n).from_address(data)
        image = np.frombuffer(raw, self.dtype).reshape(h, w).copy()  # before push_buffer
        arrived_ns = buf.get_system_timestamp()
        age = max(0.0, (time.time_ns() - arrived_ns) / 1e9) if arrived_ns else 0.0
        return Frame(
            camera=self.options.name,
            image=image,
            frame_id=self._unwrap(int(buf.get_frame_id())),
            host_time=self.clock.now() - age,
            device_time=buf.get_timestamp() / 1e9,
            retries=retries,
        )

    def _unwrap(self, raw: int) -> int:
        """GigE Vision 1.x frame ids run 1..65535 and wrap to 1 (0 is never used): a
        count that keeps increasing across the wrap. 64-bit ids are taken as they are."""
        last, self._last_id = self._last_id, raw
        if last is None or raw > 0xFFFF or last > 0xFFFF:
            self._count = raw
        else:
            self._count += (raw - last) % 0xFFFF
        return self._count
