"""The emScon twin driven by a client nobody here wrote: CESAPI (PyPI, MIT; Peter G.
Lane's pure-Python client for Leica AT4xx trackers). It sets units, initialises, sets
up stationary measurements and measures, as its author's example does, over a real
socket (127.0.0.250–.252). CESAPI reads a packet's header, then exactly the size it
announces, and decodes it by type and command: a reply of the wrong size or an unknown
type would stop its reader thread and the command would time out."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.mocks.tracker.emscon_server import EmsconTwin
from cellcal.mocks.tracker.emscon_state import SERIAL, EmsconState
from tests.lazy import Lazy

# CESAPI (and the requests and websocket it imports) loaded by the tests that use it
es = Lazy("CESAPI.packet")
CommandSync = Lazy("CESAPI.command", "CommandSync")
Connection = Lazy("CESAPI.connection", "Connection")

pytestmark = pytest.mark.timeout(90)

TRUE = np.array([1800.0, 250.0, -120.0])
SIGMA = np.diag([4e-4, 1e-4, 1e-4])


def _twin(host: str) -> EmsconTwin:
    rng = np.random.default_rng(3)
    state = EmsconState(
        sample=lambda: TRUE + np.sqrt(np.diag(SIGMA)) * rng.normal(size=3),
        covariance=lambda: SIGMA,
        started=time.monotonic(),
        time_scale=0.01,
    )
    server = EmsconTwin(state)
    server.start_tcp(host, 0)
    return server


def test_cesapi_sets_up_and_measures_from_the_twin():
    server = _twin("127.0.0.250")
    conn = Connection()
    try:
        assert server.address is not None
        conn.connect(*server.address)
        cmd = CommandSync(conn)
        units = es.SystemUnitsDataT()
        units.lenUnitType = es.ES_LU_Millimeter
        cmd.SetUnits(units)
        status = cmd.GetSystemStatus()
        assert status.lTrackerSerialNumber == SERIAL
        assert status.trackerProcessorStatus != es.ES_TPS_Initialized
        cmd.Initialize()
        assert cmd.GetSystemStatus().trackerProcessorStatus == es.ES_TPS_Initialized
        cmd.SetMeasurementMode(es.ES_MM_Stationary)
        stationary = es.StationaryModeDataT()
        stationary.lMeasTime = 1000
        cmd.SetStationaryModeParams(stationary)
        cmd.SetCoordinateSystemType(es.ES_CS_RHR)
        settings = es.SystemSettingsDataT()
        settings.weatherMonitorStatus = es.ES_WMS_ReadAndCalculateRefractions
        settings.bKeepLastPosition = 1
        settings.bSendUnsolicitedMessages = 1
        cmd.SetSystemSettings(settings)
        result = cmd.StartMeasurement()
        assert isinstance(result, es.SingleMeasResultT)
        xyz = np.array([result.dVal1, result.dVal2, result.dVal3])
        assert np.abs(xyz - TRUE).max() < 0.1
        assert result.dStd1 == pytest.approx(0.02) and result.dTemperature == 20.0
        # extended statistics: the result with covariances (type 9)
        cmd.SetStatisticMode(
            continuousMeasurements=es.ES_SM_Standard, stationaryMeasurements=es.ES_SM_Extended
        )
        result = cmd.StartMeasurement()
        assert isinstance(result, es.SingleMeasResult2T)
        assert result.dStd1 == pytest.approx(0.02) and result.dCovar12 == 0.0
        assert result.dPressure == pytest.approx(1013.25)
    finally:
        conn.disconnect()
        server.stop()
    assert server.state.settings.measure_ms == 1000


def test_cesapi_gets_the_twins_refusal_as_an_error():
    server = _twin("127.0.0.251")
    conn = Connection()
    try:
        assert server.address is not None
        conn.connect(*server.address)
        cmd = CommandSync(conn)
        with pytest.raises(Exception, match="failed with status 39"):
            cmd.StartMeasurement()  # not initialised: "tracker not initialized"
        reflectors = cmd.GetReflectors()
        assert reflectors.iTotalReflectors == 3
    finally:
        conn.disconnect()
        server.stop()
