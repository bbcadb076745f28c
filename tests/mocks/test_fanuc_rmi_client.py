"""fanuc-rmi (PyPI; an RMI client nobody here wrote, "tested on a CRX10i-A/L"), unchanged,
against ``cellcal mock fanuc-rmi`` as a process on RMI's own ports (127.0.0.16:16001 and
the session's 16002): the handshake (the client reads ``Port``, which a controller does
not send, and so always takes 16002), reset and initialise, frame and tool numbers, the
speed override, joint moves without ``TermValue`` and with consecutive sequence ids, the
joint angles read back, a refused sequence id, abort and disconnect."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

rmi = pytest.importorskip("fanuc_rmi")

pytestmark = [pytest.mark.twin, pytest.mark.timeout(90)]

HOST = "127.0.0.16"


@pytest.fixture
def controller(tmp_path: Path):
    twin = subprocess.Popen(
        [sys.executable, "-m", "cellcal", "mock", "fanuc-rmi", "--host", HOST,
         "--time-scale", "0.01"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )  # fmt: skip
    assert twin.stdout is not None
    address = twin.stdout.readline().strip()  # printed once both ports listen
    assert address == f"{HOST}:16001", twin.stderr.read() if twin.stderr else ""
    yield twin
    twin.send_signal(signal.SIGTERM)
    twin.communicate(timeout=30)
    assert twin.returncode == 0


def test_the_pypi_client_drives_the_twin(controller, tmp_path: Path, capsys):
    robot = rmi.RobotClient(host=HOST, attempts=20, retry_delay=0.1, reader_timeout=20.0)
    robot.connect()
    try:
        robot.initialize(uframe=0, utool=1)  # FRC_Reset, FRC_Initialize, FRC_SetUFrameUTool
        assert robot.get_uframe_utool() == {"UFrameNumber": 0, "UToolNumber": 1}
        robot.speed_override(50)
        start = robot.read_joint_coordinates(output_path=str(tmp_path / "j.jsonl"))
        assert start["ErrorID"] == 0
        home = [start["JointAngle"][f"J{k}"] for k in range(1, 7)]
        assert home == pytest.approx([0, -30, 40, 0, -20, 0], abs=1e-4)  # the bundled cell
        goals = [[10.0, -25.0, 35.0, 5.0, -15.0, 20.0], [0.0, -30.0, 40.0, 0.0, -20.0, 0.0]]
        for seq, goal in enumerate(goals, start=1):
            angles = {f"J{k + 1}": v for k, v in enumerate(goal)}
            robot.joint_absolute(angles, speed_percentage=40, sequence_id=seq)  # waits
            now = robot.read_joint_coordinates(output_path=str(tmp_path / "j.jsonl"))
            assert [now["JointAngle"][f"J{k}"] for k in range(1, 7)] == pytest.approx(
                goal, abs=1e-4
            )
        # a sequence id out of turn: the controller's ErrorID, read as the client reads it
        robot.joint_absolute({f"J{k}": 0.0 for k in range(1, 7)}, 40, sequence_id=9)
        assert "2556957" in capsys.readouterr().out
        assert robot.abort()["ErrorID"] == 0
    finally:
        robot.close()  # FRC_Disconnect
    lines = (tmp_path / "j.jsonl").read_text().splitlines()
    assert len(lines) == 3 and all(json.loads(x)["Command"] == "FRC_ReadJointAngles" for x in lines)
