"""The ABB driver (Robot Web Services) against its twin over real sockets (127.0.0.184–
.188): the RWS shapes and RAPID text pinned, credentials kept out of the configuration,
the move → settle → read contract, and the faults — manual mode, motors off, RAPID
stopped, mastership held elsewhere, another client, a target into a limit, wrong
credentials, a server that is not RWS, nothing listening."""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

from cellcal.drivers.abb_rws import AbbRwsOptions, AbbRwsRobot, read_credentials
from cellcal.drivers.abb_rws_dialects import (
    RWS1,
    RWS2,
    RapidValueError,
    format_jointtarget,
    parse_jointtarget,
)
from cellcal.errors import DeviceError, InputError
from cellcal.mocks.abb.rws_server import RwsTwin
from tests.robot_controllers import krc

pytest.importorskip("httpx")
pytest.importorskip("aiohttp")
pytestmark = pytest.mark.timeout(60)

HOME = [0.0, -60.0, 60.0, 0.0, 30.0, 0.0]


def twin(host: str, time_scale: float = 0.0, **kw: str) -> tuple[RwsTwin, str]:
    server = RwsTwin(krc(HOME, time_scale=time_scale), **kw)  # type: ignore[arg-type]
    h, p = server.start(host, 0)
    return server, f"http://{h}:{p}"


def robot(address: str, **kw: object) -> AbbRwsRobot:
    options = AbbRwsOptions(address=address, move_timeout_s=2.0, poll_s=0.002, **kw)  # type: ignore[arg-type]
    return AbbRwsRobot(options)


def test_shapes_and_rapid_text_are_pinned():
    assert (
        RWS1.symbol("T_ROB1", "CellCal", "cc_seq")
        == "/rw/rapid/symbol/data/RAPID/T_ROB1/CellCal/cc_seq"
    )
    assert (
        RWS2.symbol("T_ROB1", "CellCal", "cc_seq")
        == "/rw/rapid/symbol/RAPID/T_ROB1/CellCal/cc_seq/data"
    )
    assert RWS1.query("set") == {"json": "1", "action": "set"}
    assert RWS2.query("set") == {"mastership": "implicit"}
    assert RWS2.headers == {"Accept": "application/hal+json;v=2.0"}
    assert RWS2.form_type == "application/x-www-form-urlencoded;v=2.0"
    assert RWS1.item({"_embedded": {"_state": [{"opmode": "AUTO"}]}}) == {"opmode": "AUTO"}
    assert RWS2.item({"state": [{"opmode": "AUTO"}]}) == {"opmode": "AUTO"}
    assert RWS1.error(RWS1.wrap_error(-1073445862, "held")) == (-1073445862, "held")
    assert format_jointtarget([10.5, -80, 85, 0, 30, 12]) == (
        "[[10.500000,-80.000000,85.000000,0.000000,30.000000,12.000000],"
        "[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]"
    )
    # as abb-robot-client writes it, and with spaces
    text = (
        "[[10.0000,20.0000,30.0000,40.0000,50.0000,60.1235],"
        "[9000000000.0000,9E+09,9E9,9E9,9E9,9E9]]"
    )
    assert parse_jointtarget(text, "x") == [10, 20, 30, 40, 50, 60.1235]
    assert parse_jointtarget("[[1, 2, 3, 4, 5, 6], [9E9,9E9,9E9,9E9,9E9,9E9]]", "x")[5] == 6
    for bad, why in (
        ("[[1,2,3,4,5],[9E9,9E9,9E9,9E9,9E9,9E9]]", "5 robot and 6 external"),
        ("[[1,2,3,4,5,x],[9E9,9E9,9E9,9E9,9E9,9E9]]", "'x' is not a RAPID num"),
        ("[1,2,3,4,5,6]", "not a RAPID jointtarget"),
    ):
        with pytest.raises(RapidValueError, match=why):
            parse_jointtarget(bad, "cc_target")


def test_credentials_come_from_a_private_file_or_a_variable(tmp_path: Path, monkeypatch):
    secret = tmp_path / "abb.credentials"
    secret.write_text("cell operator:s3cret:with colon\n")
    secret.chmod(0o644)
    options = AbbRwsOptions(address="http://10.0.0.1", credentials=str(secret))
    with pytest.raises(InputError, match=r"readable by others \(mode 644\): chmod 600 it"):
        read_credentials(options)
    secret.chmod(0o600)
    assert read_credentials(options) == ("cell operator", "s3cret:with colon")
    monkeypatch.setenv("CELL_RWS", "admin:pw")
    assert read_credentials(AbbRwsOptions(address="http://x", credentials_env="CELL_RWS")) == (
        "admin",
        "pw",
    )
    with pytest.raises(InputError, match=r"\$NOPE is not set"):
        read_credentials(AbbRwsOptions(address="http://x", credentials_env="NOPE"))
    with pytest.raises(ValueError, match="not both"):
        AbbRwsOptions(address="http://x", credentials=str(secret), credentials_env="CELL_RWS")
    assert AbbRwsOptions(address="https://x").version() == 2
    assert AbbRwsOptions(address="http://x").version() == 1


def test_moves_settles_and_reads_the_measured_joints(tmp_path: Path):
    secret = tmp_path / "c"
    secret.write_text("cellcal:pw")
    os.chmod(secret, 0o600)
    server, address = twin("127.0.0.184", time_scale=0.02, user="cellcal", password="pw")
    try:
        with robot(address, credentials=str(secret)) as r:
            assert r.describe().maker == "ABB" and r.describe().firmware == "6.15.06.00"
            np.testing.assert_allclose(np.degrees(r.actual_joints()), HOME, atol=1e-6)
            target = np.radians([10.5, -50.25, 45.0, 5.0, 30.0, 12.0])
            r.move_joints(target, 0.5)
            np.testing.assert_allclose(r.actual_joints(), target, atol=1e-6)
        sets = [p for m, p in server.requests if m == "POST"]
        assert [s.split("?")[0].rsplit("/", 1)[1] for s in sets[:3]] == [
            "cc_target",
            "cc_speed",
            "cc_seq",
        ]
        assert all("action=set" in s and "json=1" in s for s in sets[:3])
        assert len(server.auth.sessions) >= 1  # digest once, then the session cookie
    finally:
        server.stop()


def test_faults_end_in_one_line_naming_the_robot():
    server, address = twin("127.0.0.185")
    f = server.faults
    try:
        f.opmode = "MANR"
        with pytest.raises(
            DeviceError, match=f"robot at {address}: connect refused: controller in MANR"
        ):
            robot(address).connect()
        f.opmode = "AUTO"
        # a module of another name than the one loaded: the hint names the configured one
        with pytest.raises(
            DeviceError,
            match=r"HTTP 404: no such resource: is the Other module loaded in task T_ROB1\?",
        ):
            robot(address, module="Other").connect()
        with robot(address) as r:
            f.motors_on = False
            with pytest.raises(
                DeviceError, match=r"move refused: motors are not on \(ctrlstate motoroff\)"
            ):
                r.move_joints(np.radians(HOME), 0.2)
            f.motors_on = True
            f.mastership_held = True
            with pytest.raises(
                DeviceError, match="HTTP 403: RAPID mastership is held by another client"
            ):
                r.move_joints(np.radians([1, -60, 60, 0, 30, 0]), 0.2)
            f.mastership_held = False
            # a target beyond a joint limit: RAPID stops, the driver says so
            with pytest.raises(
                DeviceError, match=r"move failed: RAPID is not running \(execution stopped\)"
            ):
                r.move_joints(np.radians([0, -60, 170, 0, 30, 0]), 0.2)
            assert server.elog and "outside reach" in server.elog[-1]
            f.running = False
            with pytest.raises(DeviceError, match="move refused: RAPID is not running"):
                r.move_joints(np.radians(HOME), 0.2)
            r._request("POST", "/rw/rapid/execution", {"regain": "continue"}, action="start")
            r.move_joints(np.radians(HOME), 0.2)
            # a loop that never acknowledges: the timeout, and RAPID stopped on the way out
            f.hang = True
            with pytest.raises(DeviceError, match=r"move not done after 2 s \(sequence \d+"):
                r.move_joints(np.radians([1, -60, 60, 0, 30, 0]), 0.2)
            assert not f.running and server.requests[-1] == (
                "POST",
                "/rw/rapid/execution?json=1&action=stop",
            )
            f.hang = False
            r._request("POST", "/rw/rapid/execution", {"regain": "continue"}, action="start")
        # the link drops (the controller goes away) in the middle of a session
        with robot(address) as r:
            server.stop()
            with pytest.raises(DeviceError, match=f"robot at {address}: cannot connect"):
                r.move_joints(np.radians(HOME), 0.2)
    finally:
        server.stop()


def test_another_client_and_wrong_credentials():
    server, address = twin("127.0.0.186", time_scale=1.0)
    try:
        with robot(address) as r:
            c = server.controller

            def intrude() -> None:
                while c.move is None:
                    threading.Event().wait(0.002)
                with c.lock:
                    c.seq = 4242

            thread = threading.Thread(target=intrude)
            thread.start()
            with pytest.raises(DeviceError, match="another client wrote cc_seq = 4242"):
                r.move_joints(np.radians([40, -60, 60, 0, 30, 0]), 1.0)
            thread.join(5)
        server.auth.password = "changed"
        server.auth.sessions.clear()
        with pytest.raises(DeviceError, match=r"refused the credentials \(HTTP 401"):
            robot(address).connect()
    finally:
        server.stop()
    with pytest.raises(DeviceError, match="cannot connect"):
        robot(address).connect()


def test_a_server_that_is_not_rws_is_one_line():
    listener = socket.create_server(("127.0.0.187", 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.recv(4096)
            body = b"<html>router login</html>"
            conn.sendall(
                b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: "
                + str(len(body)).encode()
                + b"\r\nConnection: close\r\n\r\n"
                + body
            )

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        with pytest.raises(
            DeviceError, match=r"HTTP 200, not JSON \(text/html\): is it Robot Web Services 1.0"
        ):
            robot(f"http://127.0.0.187:{port}").connect()
    finally:
        thread.join(5)
        listener.close()


def test_a_copied_configuration_finds_its_credentials_beside_it(tmp_path: Path, monkeypatch):
    """`credentials` and `tls_ca` written relative are the configuration folder's, from
    whatever folder the command runs in."""
    from cellcal.config import load_config

    folder = tmp_path / "cell"
    folder.mkdir()
    text = (Path(__file__).resolve().parents[2] / "config" / "mock-cell-abb-rws.toml").read_text()
    text = text.replace(
        '# credentials = "/etc/cellcal/abb-rws.credentials"',
        'credentials = "abb.credentials"\ntls_ca = "tls/omnicore.pem"',
    )
    (folder / "cell.toml").write_text(text)
    (folder / "abb.credentials").write_text("cellcal:pw\n")
    (folder / "abb.credentials").chmod(0o600)
    monkeypatch.chdir(tmp_path)
    robot = load_config(folder / "cell.toml").robot
    assert isinstance(robot, AbbRwsOptions)
    assert robot.credentials == str(folder.resolve() / "abb.credentials")
    assert robot.tls_ca == str(folder.resolve() / "tls" / "omnicore.pem")
    assert read_credentials(robot) == ("cellcal", "pw")
