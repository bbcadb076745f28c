"""The ``aravis`` rig against the GigE Vision twin: Aravis's fake cameras on 127.0.0.2..
in a private network namespace, the driver's camera threads joining it. Only 127.0.0.0/8
addresses are used, and only inside that namespace.

Skips, with the reason, where PyGObject/Aravis is not installed or no network namespace
can be made (not root, no user namespaces)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import numpy as np
import pydantic
import pytest

from cellcal.drivers.cameras.aravis import AravisRig, AravisRigOptions, aravis_missing
from cellcal.drivers.cameras.aravis_link import AravisLink
from cellcal.drivers.cameras.backends import rig_class
from cellcal.errors import DeviceError
from cellcal.mocks import netns
from cellcal.mocks.rig.gige_cameras import GigECameraTwin, fit, serve_rig

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.timeout(30)]


class MovingSquare:
    """Per camera: frame k (1, 2, ...) has k stamped in bytes 0..7 and a bright square at
    column 8 k; ``images[name]`` keeps what was served."""

    def __init__(self, height: int, width: int, dtype: type = np.uint8, peak: int = 200) -> None:
        self.shape, self.dtype, self.peak = (height, width), dtype, peak
        self.images: dict[str, list[np.ndarray]] = {}

    def __call__(self, name: str) -> np.ndarray:
        served = self.images.setdefault(name, [])
        k = len(served) + 1
        h, w = self.shape
        yy, xx = np.mgrid[0:h, 0:w]
        img = ((xx + 3 * yy) % 97).astype(self.dtype)
        x0 = (8 * k) % max(1, w - 16)
        img[16:32, x0 : x0 + 16] = self.peak
        img.view(np.uint8).reshape(-1)[0:8] = np.frombuffer(np.uint64(k).tobytes(), np.uint8)
        served.append(img)
        return img


def stamp(image: np.ndarray) -> int:
    return int(np.ascontiguousarray(image).view(np.uint8).reshape(-1)[0:8].view(np.uint64)[0])


def start_twin(names: list[str], source: MovingSquare, **kw: object) -> GigECameraTwin:
    reason = aravis_missing()
    if reason:
        pytest.skip(reason)
    h, w = source.shape
    try:
        return GigECameraTwin(names, source, width=w, height=h, **kw).start()  # type: ignore[arg-type]
    except netns.NamespaceUnavailableError as exc:
        pytest.skip(str(exc))


def rig_options(twin: GigECameraTwin, **camera: object) -> AravisRigOptions:
    cams = [{"name": n, "address": a, **camera} for n, a in twin.addresses.items()]
    return AravisRigOptions.model_validate({"cameras": cams, "netns": twin.netns})


@pytest.fixture
def square() -> MovingSquare:
    return MovingSquare(480, 640)


@pytest.fixture
def twin(square: MovingSquare) -> Iterator[GigECameraTwin]:
    t = start_twin(["left", "right", "top"], square)
    yield t
    t.stop()


def test_fresh_frames_ids_and_timestamps(twin: GigECameraTwin, square: MovingSquare) -> None:
    with AravisRig(rig_options(twin, exposure_us=5000.0, gain=2.0)) as rig:
        sets = [rig.grab() for _ in range(6)]
    for s in sets:
        assert s.lost == {} and s.retries == 0
        assert list(s.frames) == ["left", "right", "top"]
    for name in twin.addresses:
        frames = [s.frames[name] for s in sets]
        for f in frames:
            assert f.image.shape == (480, 640) and f.image.dtype == np.uint8
            # exactly what the source drew for this trigger: fresh, not a stale buffer
            assert np.array_equal(f.image, square.images[name][stamp(f.image) - 1])
        stamps = [stamp(f.image) for f in frames]
        assert stamps == list(range(stamps[0], stamps[0] + 6))
        ids = [f.frame_id for f in frames]
        assert ids == list(range(ids[0], ids[0] + 6))
        assert np.all(np.diff([f.device_time for f in frames]) > 0)
        assert np.all(np.diff([f.host_time for f in frames]) > 0)


@pytest.mark.parametrize("receive", ["udp", "packet"])
def test_whole_frames_through_either_socket(receive: str) -> None:
    # Sensor-sized frames (1.3 MB, a burst of 164 packets on loopback) through a UDP
    # socket with a buffer of two frames, and through Aravis's raw packet socket (as
    # root; elsewhere Aravis falls back to UDP with its own buffer).
    source = MovingSquare(1024, 1280)
    twin = start_twin(["a", "b"], source)
    try:
        with AravisRig(rig_options(twin, stream_socket=receive)) as rig:
            assert {link.udp for link in rig._links.values()} == {receive == "udp"}
            sets = [rig.grab() for _ in range(30)]
    finally:
        twin.stop()
    assert all(s.lost == {} for s in sets)
    assert sum(s.retries for s in sets) <= 2  # a rare late packet on a loaded machine
    for name in ("a", "b"):
        stamps = [stamp(s.frames[name].image) for s in sets]
        assert stamps == list(range(stamps[0], stamps[0] + 30))
        last = sets[-1].frames[name].image
        assert np.array_equal(last, source.images[name][stamps[-1] - 1])


def test_auto_takes_udp_where_rmem_max_holds_two_frames(
    twin: GigECameraTwin, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cellcal.drivers.cameras.aravis_link as link_module

    two_frames = 2 * 480 * 640
    for rmem_max, udp in ((two_frames, True), (two_frames - 1, False)):
        monkeypatch.setattr(link_module, "rmem_max", lambda v=rmem_max: v)
        with AravisRig(rig_options(twin)) as rig:
            assert all(link.udp == udp for link in rig._links.values())
            assert rig.grab().lost == {}


def test_mono16_and_region() -> None:
    source = MovingSquare(480, 640, np.uint16, peak=40000)
    twin = start_twin(["a"], source, pixel_format="Mono16")
    try:
        opts = rig_options(twin, pixel_format="Mono16", region=[0, 0, 320, 240])
        with AravisRig(opts) as rig:
            f = rig.grab().frames["a"]
    finally:
        twin.stop()
    assert f.image.shape == (240, 320) and f.image.dtype == np.uint16
    assert f.image.max() == 40000
    served = source.images["a"][stamp(f.image) - 1]
    assert np.array_equal(f.image, fit(served, 240, 320, np.dtype(np.uint16)))


def test_frame_ids_keep_counting_across_the_16_bit_wrap() -> None:
    twin = start_twin(["a"], MovingSquare(48, 64))  # the fake camera starts at 65401
    try:
        with AravisRig(rig_options(twin)) as rig:
            ids = [rig.grab().frames["a"].frame_id for _ in range(140)]
    finally:
        twin.stop()
    assert ids == list(range(ids[0], ids[0] + 140))
    assert ids[0] <= 0xFFFF < ids[-1]


def test_incomplete_frames_are_retried_then_the_camera_is_lost(twin: GigECameraTwin) -> None:
    with AravisRig(rig_options(twin, timeout_s=0.3, retries=2)) as rig:
        assert rig.grab().lost == {}
        twin.set_packet_loss("right", 1.0)
        lost = rig.grab()
        assert set(lost.frames) == {"left", "top"}
        assert "no frame after 3 attempt(s)" in lost.lost["right"]
        twin.set_packet_loss("right", 0.0)
        again = rig.grab()
    assert again.lost == {} and set(again.frames) == {"left", "right", "top"}


def test_camera_stopped_mid_series_is_lost_within_the_deadline(twin: GigECameraTwin) -> None:
    rig = AravisRig(rig_options(twin, timeout_s=0.3, retries=2))
    rig.connect()
    try:
        assert rig.grab().lost == {}
        twin.stop_camera("top")
        t0 = time.monotonic()
        s = rig.grab()
        took = time.monotonic() - t0
        assert set(s.frames) == {"left", "right"} and set(s.lost) == {"top"}
        assert took < rig.deadline_s + 0.5  # not Aravis's 2.5 s per command
        t0 = time.monotonic()
        s = rig.grab()
        assert set(s.lost) == {"top"} and time.monotonic() - t0 < 1.0
        # once Aravis gives up on the trigger (2.5 s), the camera is not triggered
        # again: lost at once in every later set, saying why
        deadline = time.monotonic() + 5.0
        while rig._workers["top"].busy and time.monotonic() < deadline:
            time.sleep(0.05)
        for _ in range(2):
            t0 = time.monotonic()
            s = rig.grab()
            assert set(s.frames) == {"left", "right"} and time.monotonic() - t0 < 1.0
            assert "trigger went unacknowledged" in s.lost["top"]
            assert not rig._workers["top"].busy
    finally:
        t0 = time.monotonic()
        rig.close()
        assert time.monotonic() - t0 < 1.5


def test_serve_rig_points_the_configured_options_at_the_twin() -> None:
    if reason := aravis_missing():
        pytest.skip(reason)
    configured = AravisRigOptions.model_validate(
        {"cameras": [{"name": "east", "address": "192.0.2.10", "pixel_format": "Mono16"}]}
    )
    source = MovingSquare(96, 128, np.uint16, peak=1000)
    try:
        running = serve_rig(configured, source, width=128, height=96)
    except netns.NamespaceUnavailableError as exc:
        pytest.skip(str(exc))
    try:
        assert running.options.cameras[0].address == "127.0.0.2"
        assert running.options.netns.startswith("/proc/")
        with AravisRig(running.options) as rig:
            f = rig.grab().frames["east"]
        assert f.image.shape == (96, 128) and f.image.dtype == np.uint16
    finally:
        running.stop()


def test_bad_address_is_one_device_error_line(twin: GigECameraTwin) -> None:
    opts = AravisRigOptions.model_validate(
        {"cameras": [{"name": "ghost", "address": "127.0.0.9"}], "netns": twin.netns}
    )
    rig = AravisRig(opts)
    t0 = time.monotonic()
    with pytest.raises(DeviceError) as err:
        rig.connect()
    assert time.monotonic() - t0 < 6.0
    message = str(err.value)
    assert message.startswith("camera ghost at 127.0.0.9: cannot open") and "\n" not in message
    rig.close()


def test_out_of_range_settings_are_refused_by_name(twin: GigECameraTwin) -> None:
    with pytest.raises(DeviceError, match=r"camera left at 127\.0\.0\.2: gain 50 outside"):
        AravisRig(rig_options(twin, gain=50.0)).connect()
    with pytest.raises(DeviceError, match=r"region 0,0,4096,480 outside the 640×480 sensor"):
        AravisRig(rig_options(twin, region=[0, 0, 4096, 480])).connect()


def test_the_twin_stays_out_of_the_host_network(twin: GigECameraTwin) -> None:
    # GVCP's port on the twin's first address is free in this thread's namespace
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.2", 3956))


def test_a_trigger_left_pending_is_woken_by_one_packet(twin: GigECameraTwin) -> None:
    # The fake camera's stall (gige_cameras' module note): a trigger it does not act on
    # for three polls gets a GVCP packet. With no client streaming, a trigger written
    # into the register stays pending, so the waker must send, and keep sending.
    lib, fake = twin._lib, twin.cameras["right"].fake
    assert lib is not None and fake is not None
    assert twin.wakes == 0
    lib.write(fake, 0x30C, 1)
    deadline = time.monotonic() + 5.0
    while twin.wakes < 2 and time.monotonic() < deadline:
        time.sleep(0.005)
    lib.write(fake, 0x30C, 0)
    assert twin.wakes >= 2
    with AravisRig(rig_options(twin)) as rig:  # the cameras still serve
        # (the first frame after acquisition starts waits out the fake camera's 100 ms
        # start-up poll, which a packet cannot shorten: wakes are sent then too)
        settled = twin.wakes
        sets = [rig.grab() for _ in range(5)]
    assert all(s.lost == {} for s in sets)
    # a trigger served is not woken: on a quiet machine none or one is; a loaded one
    # serves some triggers later than three polls, and those are woken (harmlessly)
    assert twin.wakes - settled <= len(sets)


def test_options_are_strict_and_frozen() -> None:
    ok = {"cameras": [{"name": "c1", "address": "10.0.0.2"}]}
    opts = AravisRigOptions.model_validate(ok)
    assert opts.cameras[0].pixel_format == "Mono8" and opts.cameras[0].packet_size == 8000
    assert rig_class("aravis") is AravisRig
    with pytest.raises(pydantic.ValidationError):
        opts.model_copy().cameras[0].__setattr__("gain", 3.0)
    for bad in (
        {"cameras": []},
        {"cameras": [{"name": "c1", "address": "x", "pixel_format": "RGB8"}]},
        {"cameras": [{"name": "c1", "address": "x", "exposure": 5}]},
        {"cameras": [{"name": "c1", "address": "x", "region": [0, 0, 10]}]},
        {"cameras": [{"name": "c1", "address": "x", "retries": "2"}]},
    ):
        with pytest.raises(pydantic.ValidationError):
            AravisRigOptions.model_validate(bad)


def test_frame_id_unwrap() -> None:
    opts = AravisRigOptions.model_validate({"cameras": [{"name": "c", "address": "x"}]})
    link = AravisLink(opts.cameras[0], clock=None)  # type: ignore[arg-type]
    raw = [65533, 65534, 65535, 1, 2, 5]
    assert [link._unwrap(r) for r in raw] == [65533, 65534, 65535, 65536, 65537, 65540]
    assert link._unwrap(1 << 40) == 1 << 40  # 64-bit ids as they are


def test_namespace_refusal_says_what_to_do(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(netns.os, "geteuid", lambda: 1000)
    monkeypatch.setattr(netns, "_userns_works", lambda: True)
    assert "`unshare -r <command>`" in netns._why_not(1)
    monkeypatch.setattr(netns, "_userns_works", lambda: False)
    assert "run as root (user namespaces are disabled here)" in netns._why_not(1)


def test_a_namespace_that_cannot_be_entered_is_one_device_error_line(tmp_path: object) -> None:
    if reason := aravis_missing():
        pytest.skip(reason)
    opts = AravisRigOptions.model_validate(
        {"cameras": [{"name": "c", "address": "127.0.0.2"}], "netns": "/nonexistent/ns"}
    )
    with pytest.raises(DeviceError, match=r"^camera c at 127\.0\.0\.2: .*/nonexistent/ns") as err:
        AravisRig(opts).connect()
    assert "\n" not in str(err.value)
