"""py-openshowvar (PyPI, MIT; a KUKAVARPROXY client nobody here wrote), unchanged,
against the KUKA twin (127.0.0.176): it reads and writes the controller's variables and
drives the KRL loop as it would a KR C4 running cellcal's program."""

from __future__ import annotations

import time

import pytest

from cellcal.drivers.kuka_kvp_wire import format_axes, parse_axes
from cellcal.mocks.kuka.kvp_server import KvpTwin
from tests.robot_controllers import krc

openshowvar = pytest.importorskip("py_openshowvar").openshowvar

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def kvp():
    controller = krc([0.0, -90.0, 90.0, 0.0, 0.0, 0.0], time_scale=0.01, mode="#AUT")
    twin = KvpTwin(controller)
    host, port = twin.start("127.0.0.176", 0)
    client = openshowvar(host, port)
    assert client.can_connect
    yield client, controller
    client.close()
    twin.stop()


def test_openshowvar_reads_what_a_controller_shows(kvp):
    client, _ = kvp
    assert client.read("$ROBNAME[]", debug=False) == b'"KR5ARC"'
    assert client.read("$mode_op", debug=False) == b"#AUT"  # KRL names: any case
    assert client.read("$PERI_RDY", debug=False) == b"TRUE"
    axes = client.read("$AXIS_ACT_MEAS", debug=False).decode()
    assert axes.startswith("{E6AXIS: A1 0.0, A2 -90.0, A3 90.0")
    assert parse_axes(axes, "$AXIS_ACT_MEAS") == [0, -90, 90, 0, 0, 0]
    # what the proxy answers a failure with, which the client turns into None
    assert client.read("$NO_SUCH_VARIABLE", debug=False) is None
    assert client.write("$AXIS_ACT_MEAS", "{A1 1}", debug=False) is None


def test_openshowvar_drives_the_krl_loop(kvp):
    client, controller = kvp
    target = [12.5, -75.0, 80.0, 10.0, 20.0, -30.0]
    echoed = client.write("CC_TARGET", format_axes(target), debug=False)
    assert parse_axes(echoed.decode(), "CC_TARGET") == target
    assert client.write("CC_SPEED", "100", debug=False) == b"100"
    assert client.write("CC_SEQ", "1", debug=False) == b"1"
    deadline = time.monotonic() + 10
    while client.read("CC_ACK", debug=False) != b"1":
        assert time.monotonic() < deadline, "the loop never acknowledged"
        time.sleep(0.01)
    assert client.read("$ROB_STOPPED", debug=False) == b"TRUE"
    assert parse_axes(client.read("$AXIS_ACT_MEAS", debug=False).decode(), "x") == pytest.approx(
        target, abs=1e-4
    )
    # malformed KRL text is refused and changes nothing
    assert client.write("CC_TARGET", "{E6AXIS: A1 abc}", debug=False) is None
    assert parse_axes(client.read("CC_TARGET", debug=False).decode(), "x") == target
    # in T1 the loop's variables are not writable from outside
    controller.faults.mode = "#T1"
    assert client.write("CC_SEQ", "2", debug=False) is None
