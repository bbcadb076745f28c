"""abb-robot-client (PyPI, Apache-2.0; an RWS 1.0 client nobody here wrote), unchanged,
against the ABB twin (127.0.0.189): digest authentication and the session cookie, the
panel, RAPID execution, tasks, the RAPID variables of cellcal's module, the measured
joints, the event log and RMMP — and the loop driven by hand as a real IRC5 would run it."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.mocks.abb.rws_server import RwsTwin
from tests.robot_controllers import krc

rws = pytest.importorskip("abb_robot_client.rws")
pytest.importorskip("aiohttp")

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def client():
    twin = RwsTwin(krc([0.0, -60.0, 60.0, 0.0, 30.0, 0.0], time_scale=0.01))
    host, port = twin.start("127.0.0.189", 0)
    yield rws.RWS(f"http://{host}:{port}"), twin
    twin.stop()


def test_abb_robot_client_reads_what_a_controller_shows(client):
    c, twin = client
    assert c.get_controller_state() == "motoron"
    assert c.get_operation_mode() == "AUTO"
    assert c.get_execution_state().ctrlexecstate == "running"
    assert c.get_speedratio() == 100.0
    (task,) = c.get_tasks().values()
    assert task.name == "T_ROB1" and task.motiontask
    j = c.get_jointtarget()  # degrees, as the resource gives them (the client does not convert)
    np.testing.assert_allclose(j.robax, [0, -60, 60, 0, 30, 0], atol=1e-6)
    assert c.get_rapid_variable_num("cc_ack") == 0.0
    c.request_rmmp()  # raises unless the poll says GRANTED
    assert any(path.endswith("/users/rmmp/poll?json=1") for _, path in twin.requests)
    assert len(twin.auth.sessions) >= 1


def test_abb_robot_client_drives_the_rapid_loop(client):
    c, twin = client
    target = np.radians([12.5, -45.0, 40.0, 10.0, 20.0, -30.0])
    jt = c.get_rapid_variable_jointtarget("cc_target")
    c.set_rapid_variable_jointtarget("cc_target", rws.JointTarget(target, jt.extax))
    c.set_rapid_variable_num("cc_speed", 100)
    c.set_rapid_variable_num("cc_seq", 1)
    deadline = time.monotonic() + 10
    while c.get_rapid_variable_num("cc_ack") != 1.0:
        assert time.monotonic() < deadline, "the loop never acknowledged"
        time.sleep(0.01)
    np.testing.assert_allclose(c.get_jointtarget().robax, np.degrees(target), atol=1e-4)
    # stopped from the client, RAPID says so; errors come back as ABB's codes
    c.stop()
    assert c.get_execution_state().ctrlexecstate == "stopped"
    twin.faults.mastership_held = True
    with pytest.raises(rws.ABBException) as held:
        c.set_rapid_variable_num("cc_seq", 2)
    assert held.value.code == -1073445862
    twin.faults.mastership_held = False
    # a move into a joint limit stops RAPID and writes the event log
    c.start()
    c.set_rapid_variable("cc_target", "[[0,0,170,0,0,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]")
    c.set_rapid_variable_num("cc_seq", 3)
    assert c.get_execution_state().ctrlexecstate == "stopped"
    assert any("outside reach" in e.title for e in c.read_event_log())
