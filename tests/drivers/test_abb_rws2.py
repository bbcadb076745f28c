"""The ABB driver against the twin as an OmniCore (RobotWare 7, RWS 2.0) over HTTPS on
127.0.0.188: basic authentication, the versioned headers, RWS 2.0's paths and JSON
shapes, the controller's certificate trusted through ``tls_ca`` and refused without it.
The certificate is made for the test by openssl."""

from __future__ import annotations

import shutil
import ssl
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cellcal.drivers.abb_rws import AbbRwsOptions, AbbRwsRobot
from cellcal.drivers.abb_rws_dialects import RWS2
from cellcal.errors import DeviceError
from cellcal.mocks.abb.rws_server import RwsTwin
from tests.robot_controllers import krc

pytest.importorskip("httpx")
pytest.importorskip("aiohttp")
pytestmark = pytest.mark.timeout(60)

HOST = "127.0.0.188"
HOME = [0.0, -20.0, 30.0, 0.0, 40.0, 0.0]


@pytest.fixture(scope="module")
def certificate(tmp_path_factory) -> tuple[Path, Path]:
    if shutil.which("openssl") is None:
        pytest.skip("no openssl to make a certificate")
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
         "-keyout", str(key), "-out", str(cert), "-subj", f"/CN={HOST}",
         "-addext", f"subjectAltName=IP:{HOST}"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    return cert, key


@pytest.fixture
def omnicore(certificate, monkeypatch):
    cert, key = certificate
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(cert, key)
    controller = krc(HOME)
    twin = RwsTwin(controller, user="cellcal", password="pw", dialect=RWS2, ssl_context=context)
    host, port = twin.start(HOST, 0)
    monkeypatch.setenv("CELLCAL_RWS", "cellcal:pw")
    yield twin, f"https://{host}:{port}", cert
    twin.stop()


def _robot(address: str, **kw: object) -> AbbRwsRobot:
    return AbbRwsRobot(
        AbbRwsOptions(address=address, credentials_env="CELLCAL_RWS", poll_s=0.002, **kw)  # type: ignore[arg-type]
    )


def test_an_omnicore_over_https_with_basic_authentication(omnicore):
    twin, address, cert = omnicore
    with _robot(address, tls_ca=str(cert)) as r:
        assert r.dialect.version == 2
        np.testing.assert_allclose(np.degrees(r.actual_joints()), HOME, atol=1e-6)
        target = np.radians([10.0, -25.0, 35.0, 5.0, 45.0, 10.0])
        r.move_joints(target, 0.3)
        np.testing.assert_allclose(r.actual_joints(), target, atol=1e-6)
        r.stop()
    paths = [p for _, p in twin.requests]
    assert "/rw/rapid/symbol/RAPID/T_ROB1/CellCal/cc_seq/data?mastership=implicit" in paths
    assert "/rw/panel/ctrl-state" in paths and "/rw/rapid/execution/stop" in paths
    assert not any("json=1" in p for p in paths)


def test_an_untrusted_certificate_and_rws_1_against_rws_2(omnicore):
    twin, address, _ = omnicore
    with pytest.raises(DeviceError, match=r"certificate is not trusted .*robot\.tls_ca"):
        _robot(address).connect()
    # told RWS 1.0, the driver hears the controller ask for basic authentication
    with pytest.raises(DeviceError, match=r"asks for basic authentication: it speaks RWS 2\.0"):
        _robot(address, rws=1, tls_verify=False).connect()
    twin.faults.mastership_held = True
    with (
        _robot(address, tls_verify=False) as r,
        pytest.raises(DeviceError, match="HTTP 403: RAPID mastership is held by another client"),
    ):
        r.move_joints(np.radians(HOME), 0.2)
