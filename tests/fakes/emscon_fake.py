"""A deliberately plain Leica emScon TPI server, written from the published protocol alone
(``/work/emscon_facts.md``, compiled from public copies of Leica's ``ES_C_API_Def.h``, and
``real-cells.md`` "Leica emScon TPI"), never from cellcal's own twin or driver: a second,
independent server to prove cellcal's emScon driver against.

Wire format: every packet starts ``int32 lPacketSize`` (whole packet, header included),
``int32 type``; little-endian, ``#pragma pack(4)``, every C ``long``/``int``/enum/BOOL 4
bytes, doubles at 4-byte boundaries. Every layout below is a ``struct`` format with ``<``
(no padding), which gives exactly the pack(4) offsets of the sheet because every field is
4 or 8 bytes long. One thread accepts on a TCP socket bound to a given 127.0.0.x address
(port 0: the kernel picks one, ``address`` tells it); one thread serves each connection.

Commands answered (id): GetSystemStatus 1, SetUnits 5, GetUnits 6, Initialize 7,
SetEnvironmentParams 20, GetEnvironmentParams 21, SetMeasurementMode 24,
SetCoordinateSystemType 26, SetStationaryModeParams 28, SetReflector 40, GetReflector 41,
GetReflectors 42, SetSystemSettings 47, GetSystemSettings 48, StartMeasurement 49,
StopMeasurement 52, GoBirdBath 54, FindReflector 63, SetStatisticMode 80,
GetStatisticMode 81, GoBirdBath2 95, GetMeasurementStatusInfo 122, GetTrackerInfo 132,
GetMeteoStationInfo 139. Anything else: a basic reply with ES_RS_NotImplemented (2).

Switches (``FakeSettings``): ``beam_break_at`` (the k-th measurement, 1-based, counted over
the fake's life), ``relock_after_s`` (the beam re-locks by itself after that long; None:
only FindReflector / GoBirdBath re-lock), ``warmup_s`` (the laser heats up for that long
after the fake starts), ``refuse`` (how a second client is refused), ``short_failures``
(a failing Get* reply is 16 bytes or full-size), ``failing`` (force a status on a command),
``power_on_length_unit`` and the rest below.

Choices this fake makes where the published facts leave room — each deliberately not
the obvious one, so that a driver that relies on the obvious one fails here:

1.  **Failing Get* replies are 16 bytes by default** (``short_failures=True``): a bare
    BasicCommandRT with the status, as Leica's C++ client (``CESAPIReceive::ProcessData``
    returns before reading the payload when status ≠ AllOK) tolerates. With
    ``short_failures=False`` they are full-size, payload zeroed, status set (what
    real-cells.md asks of cellcal's own twin). The sheet says which real servers do is
    not established.
2.  **Power-on units are metres, gon, °F, mbar, %RH** (length ``Meter`` 0, angle ``Gon`` 2,
    temperature ``Fahrenheit`` 1, pressure ``Mbar`` 0 — the header's "default" — humidity
    RH 0). Units, like every other setting, belong to the tracker: they survive a
    disconnect and apply to the next client. Every value on the wire honours the units
    set: lengths (coordinates, std, surface offsets, distances; the covariances dCovar12/13/
    23 and dAprioriCovar* in length² — the sheet does not say covariance or correlation,
    this fake sends covariances), angles (tracker info's angle ranges), temperature,
    pressure (kPa, mmHg = hPa/1.33322, psi, inH2O, inHg too) — incoming ones too
    (SetEnvironmentParams; FindReflector's distance is only checked to be ≥ 0).
3.  **Unsolicited status changes (type 8) come BEFORE the reply** of the Set* command that
    caused them (UnitsChanged 6, EnvironmentParamsChanged 2, ReflectorChanged 7,
    SystemSettingsChanged 8, CoordinateSystemTypeChanged 12, MeasurementModeChanged 17,
    StationaryModeParamsChanged 18, StatisticModeChanged 24), and Initialize sends
    ES_SCC_InitializationStatusChanged 151 before its reply — but only while
    ``bSendUnsolicitedMessages`` is set, which is **off at power-on**. A measurement sends
    reply, MeasStatus_Busy 26, result, MeasStatus_Ready 27; a beam break sends reply, 26,
    the type-1 error, MeasStatus_NotReady 25; a re-lock sends 27.
4.  **Power-on system settings**: weather monitor ReadAndCalculateRefractions (2) when the
    fake has a meteo station (else NotConnected 0), **ApplyTransformationParams = 1 and
    ApplyStationOrientationParams = 1**, KeepLastPosition 0, SendUnsolicitedMessages 0,
    SendReflectorPositionData 0, TryMeasurementMode 0, HasNivel 1, HasVideoCamera 0. The
    tracker holds a station orientation (+1000 mm in x) and a transformation (a 30° turn
    about z): while those flags are set, results are in that frame, not the tracker's own.
    Setting a weather monitor status other than 0 without a station answers
    ES_RS_NoWeathermonitorFound (27). SendReflectorPositionData is stored, never acted on
    (no type-7 stream).
5.  **Meteo**: with the weather monitor on (1 or 2), results and GetEnvironmentParams carry
    the station's readings, which drift a little with every measurement;
    SetEnvironmentParams is still accepted (and stored) but only used with the monitor
    off. Values outside -10..50 °C, 500..1100 hPa, 0..100 %RH answer
    ES_RS_MeteoDataOutOfRange (57).
6.  **The sensor is not initialised at power-on** (tracker processor status
    CompensationSet 4, Initialized 5 after Initialize, ``initialized`` switch). Initialize
    replies only when done (``init_s`` later); commands sent meanwhile wait in the socket and
    are answered after it. StartMeasurement before Initialize answers
    ES_RS_TrackerNotInitialized (39). Initialize leaves the beam locked on the reflector.
7.  **Warm-up** (``warmup_s``): for that long after the fake starts, GetSystemStatus says
    laser LaserHeatingUp (2) (then LaserReady 3) and both StartMeasurement and Initialize
    answer their basic reply with ES_RS_SensorNotWarmedUp (10012).
8.  **A measurement is asynchronous**: StartMeasurement answers its basic reply at once,
    the result follows after the stationary measuring time × ``time_scale``. While it is
    pending every other command but StopMeasurement answers ES_RS_ServerBusy (1) (the
    sheet's inference: no command queue at power-on). StopMeasurement cancels it: no late
    result is ever sent.
9.  **Beam break** (``beam_break_at``): the k-th measurement sends, instead of its result,
    an ES_DT_Error (type 1) packet with command StartMeasurement (49) and status
    ES_RS_NoStationaryResult (10009); the beam stays lost (ReflectorFound 2048 clear in
    GetMeasurementStatusInfo) until FindReflector, GoBirdBath (the reflector is taken to be
    in the bird bath) or ``relock_after_s``. A StartMeasurement while the beam is lost does
    not measure: its basic reply carries ES_RS_MeasurementStatusNotReady (10004). The sheet
    leaves the packet trace open; two other traces it allows, by ``beam_break_style``:
    ``"reply"`` — the k-th StartMeasurement's own basic reply carries 10009 (no result, no
    type 1); ``"after-result"`` — the k-th result is sent whole, then the beam breaks while
    the client is idle: an unsolicited ES_DT_Error with command 0 (no command: nothing is
    pending) and 10009, then MeasStatus_NotReady (25) if unsolicited messages are on (the
    header: with bSendUnsolicitedMessages "the system sends error messages at all times";
    Leica's sample: the type-1 handler is "called on unsolicited error, e.g. beam break").
    In each style all of it is sent before the client's next command is answered.
10. **Second client** (``refuse``): ``"reply"`` (default) — nothing on connect; its first
    command is answered with its own reply carrying ES_RS_MultiConnectionsNotAllowed
    (10011) (16 bytes or full-size as choice 1 says), then the socket is closed.
    ``"error"`` — an unsolicited ES_DT_Error (type 1) with command 0 and status 10011 at
    once, then the close. The slot frees when the first client disconnects.
11. **Result type** follows the statistic mode for stationary measurements: Standard (0)
    → type 2 (156 bytes, std only), Extended (1) → type 9 (204 bytes, with covariances).
    Power-on statistic mode: Standard. Results carry status 0, measMode 0, bIsTryMode as
    set by TryMeasurementMode.
12. **Packets are not always sent in one write** (``fragment=True``): every result packet
    goes out in two TCP writes a millisecond apart, split inside the header; a reply and
    the status change after it may share a write.
13. **Reflectors**: ids are arbitrary and unsorted (7, 12, 3, 21), listed in that order;
    the current one at power-on is 21 (the last listed, not the first); one 100-byte reply
    each, every one with ``iTotalReflectors``; names are UTF-16LE without a BOM,
    NUL-padded to 32 units, one of them non-ASCII ("RRR 1½″") and one exactly 32 units
    long (no NUL). An unknown id answers ES_RS_WrongParameter1 (4).
14. **Strictness**: a command whose ``lPacketSize`` is not its CT's size (per the sheet,
    pack(4)) answers ES_RS_WrongParameter (3); out-of-range enum parameters answer
    WrongParameterN (4 + N - 1); a measuring time outside 10..60000 ms answers
    ES_RS_Parameter1OutOfRangeNOK (12); SetMeasurementMode other than Stationary (0) and
    SetCoordinateSystemType other than RHR (0) answer NotImplemented (2). A packet size
    below 12 or above 64 KiB closes the connection. Client packets of a type other than 0
    are ignored.
15. GetSystemStatus's lastResultStatus is the status of the previous reply or error this
    fake sent (not this one's); lFlagsValue is always 0 (the AT401 note). Identity:
    tracker type AT401 (70), name "AT401", serial ``serial``, emScon version ``version``
    (major, minor, build), LCP firmware ``lcp_firmware``; meteo station type AT (2),
    "AT401 internal meteo", firmware ``meteo_firmware``.
"""

from __future__ import annotations

import contextlib
import math
import random
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

# ----------------------------------------------------------------------- the published facts

# ES_DataType
DT_COMMAND, DT_ERROR, DT_SINGLE, DT_STATUS_CHANGE, DT_SINGLE2 = 0, 1, 2, 8, 9

# ES_Command
GET_SYSTEM_STATUS = 1
SET_UNITS, GET_UNITS = 5, 6
INITIALIZE = 7
SET_ENVIRONMENT, GET_ENVIRONMENT = 20, 21
SET_MEAS_MODE = 24
SET_CS_TYPE = 26
SET_STATIONARY = 28
SET_REFLECTOR, GET_REFLECTOR, GET_REFLECTORS = 40, 41, 42
SET_SETTINGS, GET_SETTINGS = 47, 48
START_MEASUREMENT, STOP_MEASUREMENT = 49, 52
GO_BIRD_BATH, GO_BIRD_BATH2 = 54, 95
FIND_REFLECTOR = 63
SET_STATISTIC, GET_STATISTIC = 80, 81
GET_MEAS_STATUS_INFO = 122
GET_TRACKER_INFO = 132
GET_METEO_INFO = 139

# ES_ResultStatus
RS_OK = 0
RS_SERVER_BUSY = 1
RS_NOT_IMPLEMENTED = 2
RS_WRONG_PARAMETER = 3
RS_WRONG_PARAMETER1 = 4
RS_PARAM1_OUT_OF_RANGE_NOK = 12
RS_NO_WEATHER_MONITOR = 27
RS_TRACKER_NOT_INITIALIZED = 39
RS_METEO_OUT_OF_RANGE = 57
RS_MEAS_STATUS_NOT_READY = 10004
RS_NO_STATIONARY_RESULT = 10009
RS_MULTI_CONNECTIONS = 10011
RS_NOT_WARMED_UP = 10012

# ES_SystemStatusChange
SSC_ENVIRONMENT, SSC_UNITS, SSC_REFLECTOR, SSC_SETTINGS = 2, 6, 7, 8
SSC_CS_TYPE, SSC_MEAS_MODE, SSC_STATIONARY, SSC_STATISTIC = 12, 17, 18, 24
SSC_NOT_READY, SSC_BUSY, SSC_READY = 25, 26, 27
SSC_INITIALIZATION = 151

# ES_MeasurementStatusInfo bits
MSI_TRACKER, MSI_TRACKER_COMP, MSI_ADM, MSI_ADM_COMP = 1, 2, 4, 8
MSI_REFLECTOR_FOUND, MSI_IN_FACE1, MSI_INITIALIZED = 2048, 4096, 65536

# ES_LengthUnit: factor from millimetres
LENGTH_FROM_MM = {0: 1e-3, 1: 1.0, 2: 1e3, 3: 1 / 304.8, 4: 1 / 914.4, 5: 1 / 25.4}
LENGTH_NAMES = {0: "m", 1: "mm", 2: "µm", 3: "ft", 4: "yd", 5: "in"}
# ES_AngleUnit: factor from radians
ANGLE_FROM_RAD = {0: 1.0, 1: 180 / math.pi, 2: 200 / math.pi}
# ES_PressureUnit: factor from hPa (Mbar 0, HPascal 1, KPascal 2, MmHg 3, Psi 4, InH2O 5, InHg 6)
PRESSURE_FROM_HPA = {
    0: 1.0,
    1: 1.0,
    2: 0.1,
    3: 1 / 1.33322,
    4: 0.0145037738,
    5: 0.401463,
    6: 1 / 33.8639,
}

HEADER = struct.Struct("<ii")  # lPacketSize, type
BASIC_RT = struct.Struct("<iiii")  # size, type, command, status (also ErrorResponseT)
STATUS_CHANGE = struct.Struct("<iii")  # size, type 8, ES_SystemStatusChange

#: command packet (CT) size per command, from the sheet (pack 4)
CT_SIZE = {
    GET_SYSTEM_STATUS: 12,
    SET_UNITS: 32,
    GET_UNITS: 12,
    INITIALIZE: 12,
    SET_ENVIRONMENT: 36,
    GET_ENVIRONMENT: 12,
    SET_MEAS_MODE: 16,
    SET_CS_TYPE: 16,
    SET_STATIONARY: 20,
    SET_REFLECTOR: 16,
    GET_REFLECTOR: 12,
    GET_REFLECTORS: 12,
    SET_SETTINGS: 48,
    GET_SETTINGS: 12,
    START_MEASUREMENT: 12,
    STOP_MEASUREMENT: 12,
    GO_BIRD_BATH: 12,
    GO_BIRD_BATH2: 16,
    FIND_REFLECTOR: 20,
    SET_STATISTIC: 20,
    GET_STATISTIC: 12,
    GET_MEAS_STATUS_INFO: 12,
    GET_TRACKER_INFO: 12,
    GET_METEO_INFO: 12,
}

#: reply payload after the 16-byte BasicCommandRT, for the Get* commands (pack 4)
GET_PAYLOAD = {
    GET_SYSTEM_STATUS: struct.Struct("<10i"),  # → 56
    GET_UNITS: struct.Struct("<5i"),  # → 36
    GET_ENVIRONMENT: struct.Struct("<3d"),  # → 40
    GET_REFLECTOR: struct.Struct("<i"),  # → 20
    GET_REFLECTORS: struct.Struct("<iiid64s"),  # → 100
    GET_SETTINGS: struct.Struct("<9i"),  # → 52
    GET_STATISTIC: struct.Struct("<2i"),  # → 24
    GET_MEAS_STATUS_INFO: struct.Struct("<2i"),  # → 24
    GET_TRACKER_INFO: struct.Struct("<i64siiiiidddiiddiii"),  # → 164
    GET_METEO_INFO: struct.Struct("<i64sii"),  # → 92
}

#: SingleMeasResultT (type 2), 156 bytes: size, type, status, measMode, bIsTryMode, 17 doubles
SINGLE = struct.Struct("<iiiii17d")
#: SingleMeasResult2T (type 9), 204 bytes: size, type, status, measMode, bIsTryMode, 23 doubles
SINGLE2 = struct.Struct("<iiiii23d")

assert SINGLE.size == 156 and SINGLE2.size == 204
assert {c: 16 + s.size for c, s in GET_PAYLOAD.items()} == {
    GET_SYSTEM_STATUS: 56,
    GET_UNITS: 36,
    GET_ENVIRONMENT: 40,
    GET_REFLECTOR: 20,
    GET_REFLECTORS: 100,
    GET_SETTINGS: 52,
    GET_STATISTIC: 24,
    GET_MEAS_STATUS_INFO: 24,
    GET_TRACKER_INFO: 164,
    GET_METEO_INFO: 92,
}


def utf16_name(text: str) -> bytes:
    """``unsigned short name[32]``: UTF-16LE, no BOM, NUL-padded (no NUL at 32 units)."""
    raw = text.encode("utf-16-le")[:64]
    return raw.ljust(64, b"\0")


def temperature_out(celsius: float, unit: int) -> float:
    return celsius * 1.8 + 32 if unit == 1 else celsius


def temperature_in(value: float, unit: int) -> float:
    return (value - 32) / 1.8 if unit == 1 else value


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class Reflector:
    id: int
    target_type: int  # ES_TargetType
    surface_offset_mm: float
    name: str


DEFAULT_REFLECTORS = (
    Reflector(7, 5, 19.05, "RRR 1.5in"),
    Reflector(12, 6, 6.35, "RRR 1½″"),
    Reflector(3, 7, 19.05, "BRR 1.5in break resistant target"),  # 32 units: no NUL
    Reflector(21, 9, 6.35, "TBR 0.5in"),
)
assert len(DEFAULT_REFLECTORS[2].name) == 32


@dataclass
class FakeSettings:
    host: str
    port: int = 0
    serial: int = 390917
    version: tuple[int, int, int] = (3, 6, 517)
    lcp_firmware: tuple[int, int] = (2, 14)
    meteo_firmware: tuple[int, int] = (1, 7)
    has_meteo_station: bool = True
    #: the air the station reads (°C, hPa, %RH) at the first measurement
    station_air: tuple[float, float, float] = (21.37, 987.65, 43.21)
    #: the reflector's true position in the tracker's own frame (mm)
    target_mm: tuple[float, float, float] = (1834.125, -2217.5, 412.0625)
    noise_mm: float = 0.004
    reflectors: tuple[Reflector, ...] = DEFAULT_REFLECTORS
    current_reflector: int = 21
    power_on_length_unit: int = 0  # metres
    initialized: bool = False
    init_s: float = 0.2
    warmup_s: float = 0.0
    find_s: float = 0.05
    #: the stationary measuring time is waited for × this
    time_scale: float = 0.01
    beam_break_at: tuple[int, ...] = ()
    #: how a beam break is told (choice 9): "error", "reply" or "after-result"
    beam_break_style: Literal["error", "reply", "after-result"] = "error"
    relock_after_s: float | None = None
    short_failures: bool = True
    #: command id → status to answer it with (the reply's own size rule applies)
    failing: dict[int, int] = field(default_factory=dict)
    refuse: Literal["reply", "error"] = "reply"
    fragment: bool = True
    seed: int = 31


@dataclass
class Sent:
    """One measurement result the fake sent: as on the wire and in mm / °C / hPa / %RH."""

    packet_type: int
    wire: tuple[float, ...]
    length_unit: int
    xyz_mm: tuple[float, float, float]
    cov_mm2: tuple[tuple[float, ...], ...]
    meteo: tuple[float, float, float]


class _Conn:
    def __init__(self, sock: socket.socket, fragment: bool) -> None:
        self.sock = sock
        self.fragment = fragment
        self.lock = threading.Lock()
        self.alive = True

    def send(self, *packets: bytes, split: bool = False) -> None:
        with self.lock:
            if not self.alive:
                return
            try:
                for packet in packets:
                    if split and self.fragment:
                        self.sock.sendall(packet[:6])
                        time.sleep(0.001)
                        self.sock.sendall(packet[6:])
                    else:
                        self.sock.sendall(packet)
            except OSError:
                self.alive = False

    def close(self) -> None:
        with self.lock:
            self.alive = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    data = bytearray()
    while len(data) < n:
        try:
            chunk = sock.recv(n - len(data))
        except OSError:
            return None
        if not chunk:
            return None
        data += chunk
    return bytes(data)


# ------------------------------------------------------------------------------- server


class EmsconFake:
    """The server. ``start()`` binds and listens before it returns (``listening`` is set
    then); ``close()`` stops it. Records: ``received`` (every command packet, in order,
    as (command id, raw bytes)), ``replies`` (every type-0 reply as (command, status,
    size)), ``sent`` (every measurement result), ``errors_sent`` (every type-1 packet as
    (command, status)), ``refused`` (second clients turned away), ``measurements``
    (measurements finished or broken); ``idle`` is set while no client holds the slot."""

    def __init__(self, settings: FakeSettings) -> None:
        self.s = settings
        self.listening = threading.Event()
        #: set while no client holds the connection slot
        self.idle = threading.Event()
        self.idle.set()
        self.received: list[tuple[int, bytes]] = []
        self.sent: list[Sent] = []
        self.replies: list[tuple[int, int, int]] = []
        self.errors_sent: list[tuple[int, int]] = []
        self.refused = 0
        self.measurements = 0
        self._lock = threading.RLock()
        self._rng = random.Random(settings.seed)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._timers: list[threading.Timer] = []
        self._active: _Conn | None = None
        self._conns: list[_Conn] = []
        self._pending: threading.Event | None = None  # set = cancel
        self._listener: socket.socket | None = None
        self._t0 = time.monotonic()
        # the tracker's state (survives connections)
        self.units = [settings.power_on_length_unit, 2, 1, 0, 0]
        self.manual_air = (20.0, 1013.25, 50.0)
        self.settings = [2 if settings.has_meteo_station else 0, 1, 1, 0, 0, 0, 0, 1, 0]
        self.meas_mode = 0
        self.cs_type = 0
        self.stationary = (1000, 1)
        self.statistic = (0, 0)
        self.reflector = settings.current_reflector
        self.initialized = settings.initialized
        self.locked = True
        self.last_status = RS_OK

    # -- life

    @property
    def address(self) -> str:
        assert self._listener is not None
        host, port = self._listener.getsockname()[:2]
        return f"{host}:{port}"

    @property
    def port(self) -> int:
        assert self._listener is not None
        return int(self._listener.getsockname()[1])

    def start(self) -> EmsconFake:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.s.host, self.s.port))
        listener.listen(4)
        listener.settimeout(0.1)
        self._listener = listener
        self._t0 = time.monotonic()
        self._spawn(self._accept_loop, "emscon-fake-accept")
        self.listening.set()
        return self

    def close(self) -> None:
        self._stop.set()
        for timer in self._timers:
            timer.cancel()
        with self._lock:
            if self._pending is not None:
                self._pending.set()
            conns = list(self._conns)
        for conn in conns:
            conn.close()
        if self._listener is not None:
            self._listener.close()
        for thread in self._threads:
            thread.join(timeout=5)

    def __enter__(self) -> EmsconFake:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _spawn(self, target: Callable[..., None], name: str, *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def warming(self) -> bool:
        return time.monotonic() - self._t0 < self.s.warmup_s

    def commands(self) -> list[int]:
        """The command ids received so far, in order."""
        with self._lock:
            return [cmd for cmd, _ in self.received]

    # -- connections

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.settimeout(None)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _Conn(sock, self.s.fragment)
            with self._lock:
                self._conns.append(conn)
                second = self._active is not None
                if not second:
                    self._active = conn
                    self.idle.clear()
            if second:
                self._spawn(self._refuse, "emscon-fake-refuse", conn)
            else:
                self._spawn(self._serve, "emscon-fake-conn", conn)

    def _refuse(self, conn: _Conn) -> None:
        with self._lock:
            self.refused += 1
        if self.s.refuse == "error":
            self.errors_sent.append((0, RS_MULTI_CONNECTIONS))
            conn.send(BASIC_RT.pack(16, DT_ERROR, 0, RS_MULTI_CONNECTIONS))
        else:
            packet = self._read_packet(conn)
            if packet is not None and len(packet) >= 12:
                cmd = struct.unpack_from("<i", packet, 8)[0]
                conn.send(self._failure(cmd, RS_MULTI_CONNECTIONS, remember=False))
        conn.close()

    def _read_packet(self, conn: _Conn) -> bytes | None:
        head = _recv_exact(conn.sock, 4)
        if head is None:
            return None
        (size,) = struct.unpack("<i", head)
        if size < 12 or size > 65536:
            return None
        rest = _recv_exact(conn.sock, size - 4)
        return None if rest is None else head + rest

    def _serve(self, conn: _Conn) -> None:
        try:
            while not self._stop.is_set():
                packet = self._read_packet(conn)
                if packet is None:
                    break
                _, kind, cmd = struct.unpack_from("<iii", packet)
                if kind != DT_COMMAND:
                    continue
                with self._lock:
                    self.received.append((cmd, packet))
                self._dispatch(conn, cmd, packet)
        finally:
            with self._lock:
                if self._pending is not None:
                    self._pending.set()
                    self._pending = None
                if self._active is conn:
                    self._active = None
            conn.close()
            with self._lock:
                if self._active is None:
                    self.idle.set()

    # -- packets out

    def _reply(
        self, cmd: int, status: int, payload: bytes = b"", *, remember: bool = True
    ) -> bytes:
        if remember:
            self.last_status = status
        self.replies.append((cmd, status, 16 + len(payload)))
        return BASIC_RT.pack(16 + len(payload), DT_COMMAND, cmd, status) + payload

    def _failure(self, cmd: int, status: int, *, remember: bool = True) -> bytes:
        """The reply to ``cmd`` failing with ``status``: choice 1."""
        layout = GET_PAYLOAD.get(cmd)
        payload = b"" if layout is None or self.s.short_failures else bytes(layout.size)
        return self._reply(cmd, status, payload, remember=remember)

    def _ssc(self, conn: _Conn, *changes: int) -> None:
        if self.settings[4]:  # bSendUnsolicitedMessages
            conn.send(*(STATUS_CHANGE.pack(12, DT_STATUS_CHANGE, c) for c in changes))

    def _ssc_bytes(self, *changes: int) -> bytes:
        if not self.settings[4]:
            return b""
        return b"".join(STATUS_CHANGE.pack(12, DT_STATUS_CHANGE, c) for c in changes)

    # -- commands

    def _dispatch(self, conn: _Conn, cmd: int, packet: bytes) -> None:
        with self._lock:
            busy = self._pending is not None
        if cmd in CT_SIZE and len(packet) != CT_SIZE[cmd]:
            conn.send(self._failure(cmd, RS_WRONG_PARAMETER))
            return
        if busy and cmd != STOP_MEASUREMENT:
            conn.send(self._failure(cmd, RS_SERVER_BUSY))
            return
        if cmd in self.s.failing:
            conn.send(self._failure(cmd, self.s.failing[cmd]))
            return
        handler = getattr(self, f"_cmd_{cmd}", None)
        if handler is None:
            conn.send(self._reply(cmd, RS_NOT_IMPLEMENTED))
            return
        handler(conn, packet)

    def _set(self, conn: _Conn, cmd: int, status: int, change: int) -> None:
        """A Set* command's answer: its status change first (choice 3), then the reply."""
        if status == RS_OK:
            self._ssc(conn, change)
        conn.send(self._reply(cmd, status))

    def _cmd_1(self, conn: _Conn, packet: bytes) -> None:  # GetSystemStatus
        last = self.last_status
        payload = GET_PAYLOAD[GET_SYSTEM_STATUS].pack(
            last,
            5 if self.initialized else 4,  # ES_TrackerProcessorStatus
            2 if self.warming() else 3,  # ES_LaserProcessorStatus
            2,  # ES_ADMStatus: ADMReady
            *self.s.version,
            self.settings[0],
            0,  # lFlagsValue: always 0 on an AT401
            self.s.serial,
        )
        conn.send(self._reply(GET_SYSTEM_STATUS, RS_OK, payload))

    def _cmd_5(self, conn: _Conn, packet: bytes) -> None:  # SetUnits
        values = struct.unpack_from("<5i", packet, 12)
        limits = (5, 2, 1, 6, 0)
        for i, (value, top) in enumerate(zip(values, limits, strict=True)):
            if not 0 <= value <= top:
                conn.send(self._reply(SET_UNITS, RS_WRONG_PARAMETER1 + i))
                return
        self.units = list(values)
        self._set(conn, SET_UNITS, RS_OK, SSC_UNITS)

    def _cmd_6(self, conn: _Conn, packet: bytes) -> None:  # GetUnits
        conn.send(self._reply(GET_UNITS, RS_OK, GET_PAYLOAD[GET_UNITS].pack(*self.units)))

    def _cmd_7(self, conn: _Conn, packet: bytes) -> None:  # Initialize
        if self.warming():
            conn.send(self._reply(INITIALIZE, RS_NOT_WARMED_UP))
            return
        if self._stop.wait(self.s.init_s):
            return
        self.initialized = True
        self.locked = True
        self._ssc(conn, SSC_INITIALIZATION)
        conn.send(self._reply(INITIALIZE, RS_OK))

    def air(self) -> tuple[float, float, float]:
        """The air the results carry now (°C, hPa, %RH): choice 5."""
        if self.settings[0] in (1, 2) and self.s.has_meteo_station:
            t, p, h = self.s.station_air
            k = self.measurements
            return (t + 0.011 * k, p - 0.07 * k, h + 0.13 * k)
        return self.manual_air

    def _cmd_20(self, conn: _Conn, packet: bytes) -> None:  # SetEnvironmentParams
        t, p, h = struct.unpack_from("<3d", packet, 12)
        t = temperature_in(t, self.units[2])
        p = p / PRESSURE_FROM_HPA[self.units[3]]
        if not (-10 <= t <= 50 and 500 <= p <= 1100 and 0 <= h <= 100):
            conn.send(self._reply(SET_ENVIRONMENT, RS_METEO_OUT_OF_RANGE))
            return
        self.manual_air = (t, p, h)
        self._set(conn, SET_ENVIRONMENT, RS_OK, SSC_ENVIRONMENT)

    def _cmd_21(self, conn: _Conn, packet: bytes) -> None:  # GetEnvironmentParams
        t, p, h = self.air()
        payload = GET_PAYLOAD[GET_ENVIRONMENT].pack(
            temperature_out(t, self.units[2]), p * PRESSURE_FROM_HPA[self.units[3]], h
        )
        conn.send(self._reply(GET_ENVIRONMENT, RS_OK, payload))

    def _cmd_24(self, conn: _Conn, packet: bytes) -> None:  # SetMeasurementMode
        (mode,) = struct.unpack_from("<i", packet, 12)
        if mode != 0:
            conn.send(self._reply(SET_MEAS_MODE, RS_NOT_IMPLEMENTED))
            return
        self.meas_mode = mode
        self._set(conn, SET_MEAS_MODE, RS_OK, SSC_MEAS_MODE)

    def _cmd_26(self, conn: _Conn, packet: bytes) -> None:  # SetCoordinateSystemType
        (cs,) = struct.unpack_from("<i", packet, 12)
        if cs != 0:
            status = RS_NOT_IMPLEMENTED if 0 <= cs <= 7 else RS_WRONG_PARAMETER1
            conn.send(self._reply(SET_CS_TYPE, status))
            return
        self.cs_type = cs
        self._set(conn, SET_CS_TYPE, RS_OK, SSC_CS_TYPE)

    def _cmd_28(self, conn: _Conn, packet: bytes) -> None:  # SetStationaryModeParams
        ms, adm = struct.unpack_from("<2i", packet, 12)
        if not 10 <= ms <= 60000:
            conn.send(self._reply(SET_STATIONARY, RS_PARAM1_OUT_OF_RANGE_NOK))
            return
        if adm not in (0, 1):
            conn.send(self._reply(SET_STATIONARY, RS_WRONG_PARAMETER1 + 1))
            return
        self.stationary = (ms, adm)
        self._set(conn, SET_STATIONARY, RS_OK, SSC_STATIONARY)

    def _cmd_40(self, conn: _Conn, packet: bytes) -> None:  # SetReflector
        (rid,) = struct.unpack_from("<i", packet, 12)
        if rid not in {r.id for r in self.s.reflectors}:
            conn.send(self._reply(SET_REFLECTOR, RS_WRONG_PARAMETER1))
            return
        self.reflector = rid
        self._set(conn, SET_REFLECTOR, RS_OK, SSC_REFLECTOR)

    def _cmd_41(self, conn: _Conn, packet: bytes) -> None:  # GetReflector
        payload = GET_PAYLOAD[GET_REFLECTOR].pack(self.reflector)
        conn.send(self._reply(GET_REFLECTOR, RS_OK, payload))

    def _cmd_42(self, conn: _Conn, packet: bytes) -> None:  # GetReflectors
        scale = LENGTH_FROM_MM[self.units[0]]
        total = len(self.s.reflectors)
        replies = [
            self._reply(
                GET_REFLECTORS,
                RS_OK,
                GET_PAYLOAD[GET_REFLECTORS].pack(
                    total, r.id, r.target_type, r.surface_offset_mm * scale, utf16_name(r.name)
                ),
            )
            for r in self.s.reflectors
        ]
        conn.send(*replies)

    def _cmd_47(self, conn: _Conn, packet: bytes) -> None:  # SetSystemSettings
        values = list(struct.unpack_from("<9i", packet, 12))
        if not 0 <= values[0] <= 2:
            conn.send(self._reply(SET_SETTINGS, RS_WRONG_PARAMETER1))
            return
        for i, flag in enumerate(values[1:], start=1):
            if flag not in (0, 1):
                conn.send(self._reply(SET_SETTINGS, RS_WRONG_PARAMETER1 + i))
                return
        if values[0] != 0 and not self.s.has_meteo_station:
            conn.send(self._reply(SET_SETTINGS, RS_NO_WEATHER_MONITOR))
            return
        self.settings = values
        self._set(conn, SET_SETTINGS, RS_OK, SSC_SETTINGS)

    def _cmd_48(self, conn: _Conn, packet: bytes) -> None:  # GetSystemSettings
        payload = GET_PAYLOAD[GET_SETTINGS].pack(*self.settings)
        conn.send(self._reply(GET_SETTINGS, RS_OK, payload))

    def _cmd_80(self, conn: _Conn, packet: bytes) -> None:  # SetStatisticMode
        stationary, continuous = struct.unpack_from("<2i", packet, 12)
        for i, value in enumerate((stationary, continuous)):
            if value not in (0, 1):
                conn.send(self._reply(SET_STATISTIC, RS_WRONG_PARAMETER1 + i))
                return
        self.statistic = (stationary, continuous)
        self._set(conn, SET_STATISTIC, RS_OK, SSC_STATISTIC)

    def _cmd_81(self, conn: _Conn, packet: bytes) -> None:  # GetStatisticMode
        payload = GET_PAYLOAD[GET_STATISTIC].pack(*self.statistic)
        conn.send(self._reply(GET_STATISTIC, RS_OK, payload))

    def _cmd_122(self, conn: _Conn, packet: bytes) -> None:  # GetMeasurementStatusInfo
        flags = MSI_TRACKER | MSI_TRACKER_COMP | MSI_ADM | MSI_ADM_COMP | MSI_IN_FACE1
        if self.locked:
            flags |= MSI_REFLECTOR_FOUND
        if self.initialized:
            flags |= MSI_INITIALIZED
        payload = GET_PAYLOAD[GET_MEAS_STATUS_INFO].pack(self.last_status, flags)
        conn.send(self._reply(GET_MEAS_STATUS_INFO, RS_OK, payload))

    def _cmd_132(self, conn: _Conn, packet: bytes) -> None:  # GetTrackerInfo
        length = LENGTH_FROM_MM[self.units[0]]
        angle = ANGLE_FROM_RAD[self.units[1]]
        payload = GET_PAYLOAD[GET_TRACKER_INFO].pack(
            70,  # ES_LTS_AT401
            utf16_name("AT401"),
            self.s.serial,
            4711,  # lCompensationIdNumber
            1,  # bHasADM
            0,  # bHasOverviewCamera
            1,  # bHasNivel
            0.0,  # dNivelMountOffset
            160000.0 * length,  # dMaxDistance
            1500.0 * length,  # dMinDistance
            1000,  # iMaxDataRate
            2,  # iNumberOfFaces
            2 * math.pi * angle,  # dHzAngleRange
            math.radians(290) * angle,  # dVtAngleRange
            1,  # ES_TrkAccuracyModel 2005
            *self.s.lcp_firmware,
        )
        conn.send(self._reply(GET_TRACKER_INFO, RS_OK, payload))

    def _cmd_139(self, conn: _Conn, packet: bytes) -> None:  # GetMeteoStationInfo
        if not self.s.has_meteo_station:
            conn.send(self._failure(GET_METEO_INFO, RS_NO_WEATHER_MONITOR))
            return
        payload = GET_PAYLOAD[GET_METEO_INFO].pack(
            2, utf16_name("AT401 internal meteo"), *self.s.meteo_firmware
        )
        conn.send(self._reply(GET_METEO_INFO, RS_OK, payload))

    # -- the beam

    def _relock(self, conn: _Conn | None, cmd: int | None) -> None:
        if cmd is not None and self._stop.wait(self.s.find_s):
            return
        with self._lock:
            was = self.locked
            self.locked = True
        if conn is not None and not was:
            self._ssc(conn, SSC_READY)
        if conn is not None and cmd is not None:
            conn.send(self._reply(cmd, RS_OK))

    def _cmd_63(self, conn: _Conn, packet: bytes) -> None:  # FindReflector
        (distance,) = struct.unpack_from("<d", packet, 12)
        if not distance >= 0:
            conn.send(self._reply(FIND_REFLECTOR, RS_WRONG_PARAMETER1))
            return
        self._relock(conn, FIND_REFLECTOR)

    def _cmd_54(self, conn: _Conn, packet: bytes) -> None:  # GoBirdBath
        self._relock(conn, GO_BIRD_BATH)

    def _cmd_95(self, conn: _Conn, packet: bytes) -> None:  # GoBirdBath2
        self._relock(conn, GO_BIRD_BATH2)

    def _timed_relock(self) -> None:
        with self._lock:
            conn = self._active
        self._relock(conn, None)

    # -- measuring

    def _cmd_52(self, conn: _Conn, packet: bytes) -> None:  # StopMeasurement
        with self._lock:
            if self._pending is not None:
                self._pending.set()
                self._pending = None
        conn.send(self._reply(STOP_MEASUREMENT, RS_OK))

    def _cmd_49(self, conn: _Conn, packet: bytes) -> None:  # StartMeasurement
        if self.warming():
            conn.send(self._reply(START_MEASUREMENT, RS_NOT_WARMED_UP))
            return
        if not self.initialized:
            conn.send(self._reply(START_MEASUREMENT, RS_TRACKER_NOT_INITIALIZED))
            return
        if not self.locked:
            conn.send(self._reply(START_MEASUREMENT, RS_MEAS_STATUS_NOT_READY))
            return
        with self._lock:
            k = self.measurements + 1
            if self.s.beam_break_style == "reply" and k in self.s.beam_break_at:
                self.measurements = k
                reply = self._reply(START_MEASUREMENT, RS_NO_STATIONARY_RESULT)
                self._lose_beam(conn, reply)
                return
            cancel = threading.Event()
            self._pending = cancel
        conn.send(self._reply(START_MEASUREMENT, RS_OK) + self._ssc_bytes(SSC_BUSY))
        self._spawn(self._measure, "emscon-fake-measure", conn, cancel)

    def _lose_beam(self, conn: _Conn, *packets: bytes) -> None:
        """The beam breaks: ``packets`` (the error), MeasStatus_NotReady, the re-lock
        timer. Call locked."""
        self.locked = False
        self.last_status = RS_NO_STATIONARY_RESULT
        conn.send(*packets, self._ssc_bytes(SSC_NOT_READY))
        if self.s.relock_after_s is not None:
            timer = threading.Timer(self.s.relock_after_s, self._timed_relock)
            timer.daemon = True
            self._timers.append(timer)
            timer.start()

    def _measure(self, conn: _Conn, cancel: threading.Event) -> None:
        if cancel.wait(self.stationary[0] / 1000 * self.s.time_scale):
            return
        with self._lock:
            if cancel.is_set() or self._pending is not cancel:
                return
            self._pending = None
            self.measurements += 1
            k = self.measurements
            broken = k in self.s.beam_break_at
            if broken and self.s.beam_break_style == "error":
                self.errors_sent.append((START_MEASUREMENT, RS_NO_STATIONARY_RESULT))
                error = BASIC_RT.pack(16, DT_ERROR, START_MEASUREMENT, RS_NO_STATIONARY_RESULT)
                self._lose_beam(conn, error)
                return
            packet = self._result()
            conn.send(packet, split=True)
            conn.send(self._ssc_bytes(SSC_READY))
            if broken and self.s.beam_break_style == "after-result":
                # still locked, so the client's next command waits for this
                self.errors_sent.append((0, RS_NO_STATIONARY_RESULT))
                self._lose_beam(conn, BASIC_RT.pack(16, DT_ERROR, 0, RS_NO_STATIONARY_RESULT))

    def _frame(self, xyz: tuple[float, float, float]) -> tuple[float, float, float]:
        """The tracker's own frame → the frame the settings ask for (choice 4)."""
        x, y, z = xyz
        if self.settings[2]:  # station orientation: +1000 mm in x
            x += 1000.0
        if self.settings[1]:  # transformation: 30° about z
            c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
            x, y = c * x - s * y, s * x + c * y
        return x, y, z

    def _result(self) -> bytes:
        """The next result packet (type 2 or 9), recorded in ``sent``. Call locked."""
        rng = self._rng
        true = self.s.target_mm
        xyz = self._frame(
            (
                true[0] + rng.gauss(0, self.s.noise_mm),
                true[1] + rng.gauss(0, self.s.noise_mm),
                true[2] + rng.gauss(0, self.s.noise_mm),
            )
        )
        std = (0.0041 + 0.0002 * rng.random(), 0.0052, 0.0063)
        rho = (0.31, -0.22, 0.17)  # 12, 13, 23
        cov12 = rho[0] * std[0] * std[1]
        cov13 = rho[1] * std[0] * std[2]
        cov23 = rho[2] * std[1] * std[2]
        cov: tuple[tuple[float, ...], ...] = (
            (std[0] ** 2, cov12, cov13),
            (cov12, std[1] ** 2, cov23),
            (cov13, cov23, std[2] ** 2),
        )
        total = math.sqrt(sum(s * s for s in std))
        apriori = (0.010, 0.011, 0.012)
        apriori_total = math.sqrt(sum(s * s for s in apriori))
        meteo = self.air()
        lu = self.units[0]
        f = LENGTH_FROM_MM[lu]
        wire_meteo = (
            temperature_out(meteo[0], self.units[2]),
            meteo[1] * PRESSURE_FROM_HPA[self.units[3]],
            meteo[2],
        )
        head = (0, self.meas_mode, self.settings[6])
        if self.statistic[0] == 1:
            values = (
                *(v * f for v in xyz),
                *(s * f for s in std),
                total * f,
                cov12 * f * f,
                cov13 * f * f,
                cov23 * f * f,
                0.0012 * f,  # pointing errors H, V, D
                0.0011 * f,
                0.0009 * f,
                *(a * f for a in apriori),
                apriori_total * f,
                0.1 * apriori[0] * apriori[1] * f * f,
                0.0,
                0.0,
                *wire_meteo,
            )
            packet = SINGLE2.pack(SINGLE2.size, DT_SINGLE2, *head, *values)
            kind = DT_SINGLE2
        else:
            values = (
                *(v * f for v in xyz),
                *(s * f for s in std),
                total * f,
                0.0012 * f,
                0.0011 * f,
                0.0009 * f,
                *(a * f for a in apriori),
                apriori_total * f,
                *wire_meteo,
            )
            packet = SINGLE.pack(SINGLE.size, DT_SINGLE, *head, *values)
            kind = DT_SINGLE
            cov = tuple(tuple(cov[i][j] if i == j else 0.0 for j in range(3)) for i in range(3))
        self.last_status = RS_OK
        self.sent.append(Sent(kind, values, lu, xyz, cov, meteo))
        return packet
