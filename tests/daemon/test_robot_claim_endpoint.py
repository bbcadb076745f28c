"""The robot's claim is the robot, however cellcal reaches it, and the driver connects
where the claim was resolved to.

- A UR controller configured once with the ``ur`` driver (ur_rtde) and once with the
  ``modbus`` driver (its Modbus TCP server, port 502) on the same host is one claim:
  the second is refused, whichever came first, whatever the spelling of the host.
- Once the claim has resolved the robot's host, the driver connects to that address:
  a name resolved again (by the driver, the system's resolver) that answers otherwise
  meanwhile would reach a machine nobody claimed.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cellcal.campaign.locks import RobotClaim
from cellcal.campaign.runner import start_campaign
from cellcal.config import config_from_dict
from cellcal.errors import CampaignError
from cellcal.files.models import load_model
from cellcal.mocks.modbus import server as modbus_robot_server
from cellcal.mocks.simulated_cell import SimulatedCell
from cellcal.mocks.tracker import server as tracker_server
from tests.conftest import tracker_cell

pytestmark = pytest.mark.timeout(120)

NAME = "robot.cellcal.test"
#: Where NAME resolves for the claim, and where a second resolution would send it.
CLAIMED, ELSEWHERE = "127.0.0.163", "127.0.0.166"


@pytest.mark.parametrize(
    ("first", "second"),
    [
        (("ur", "127.0.0.1"), ("modbus", "localhost")),
        (("ur", "localhost"), ("modbus", "127.0.0.1:502")),
        (("modbus", "127.0.0.1"), ("ur", "0x7f000001")),
        (("modbus", "[::ffff:127.0.0.1]:502"), ("ur", "127.0.0.1")),
    ],
)
def test_one_ur_through_two_drivers_is_one_claim(
    locks: Path, first: tuple[str, str], second: tuple[str, str]
) -> None:
    with RobotClaim(*first, "the cellcal service on /data/a.db"):
        with (
            pytest.raises(CampaignError, match="is claimed by the cellcal service") as info,
            RobotClaim(*second, "cellcal run on /data/b.db"),
        ):
            pytest.fail(f"{second} claimed the robot {first} holds")
        assert f"the {second[0]} robot at {second[1]}" in str(info.value)
        assert "\n" not in str(info.value)
    with RobotClaim(*second, "next"):  # released with the first claim
        pass  # taken without a refusal: the point of the test


def test_other_ports_of_the_host_stay_other_robots(locks: Path) -> None:
    """As before: a Modbus server on another port of the host is another controller."""
    with RobotClaim("ur", "127.0.0.1", "service"), RobotClaim("modbus", "127.0.0.1:1502", "run"):
        pass  # both taken at once: two robots


def _resolving(monkeypatch: pytest.MonkeyPatch, first: str = CLAIMED) -> list[str]:
    """NAME resolves to ``first`` the first time, to ELSEWHERE after (a DNS answer that
    changed, a second record); every other name as the system resolves it. The list
    returned grows with each answer given for NAME."""
    real = socket.getaddrinfo
    answers: list[str] = []

    def getaddrinfo(host: Any, port_: Any, *args: Any, **kwargs: Any) -> Any:
        if host != NAME:
            return real(host, port_, *args, **kwargs)
        ip = first if not answers else ELSEWHERE
        answers.append(ip)
        return real(ip, port_, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    return answers


def test_the_claim_gives_the_address_it_resolved(
    locks: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _resolving(monkeypatch)
    with RobotClaim("modbus", f"{NAME}:1502", "run") as claim:
        assert claim.address == f"{CLAIMED}:1502"
    _resolving(monkeypatch)
    with RobotClaim("ur", NAME, "run") as claim:
        assert claim.address == CLAIMED  # a UR's ports are fixed: its host alone
    with RobotClaim("modbus", "[::1]:502", "run") as claim:
        assert claim.address == "[::1]:502"


@pytest.fixture
def twins() -> Iterator[tuple[Any, Any, SimulatedCell]]:
    """The tracker cell's Modbus robot twin and tracker twin, in this process."""
    config = tracker_cell()
    cell = SimulatedCell(config, load_model(config.robot.model).model, config.simulation.seed)
    robot = modbus_robot_server.serve(config.robot, cell, 0.0)  # type: ignore[arg-type]
    try:
        tracker = tracker_server.serve(config.sensor[0], cell, 0.0)  # type: ignore[arg-type]
    except BaseException:
        robot.stop()
        raise
    try:
        yield robot, tracker, cell
    finally:
        tracker.stop()
        robot.stop()


@pytest.mark.twin
def test_the_driver_connects_where_the_claim_resolved(
    locks: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    twins: tuple[Any, Any, SimulatedCell],
) -> None:
    robot, tracker, _ = twins
    twin_host, port = robot.options.address.rsplit(":", 1)
    # The robot's name resolves to its twin's address for the claim; resolved again it
    # would reach a decoy on the same port elsewhere, which must see no connection.
    decoy = socket.create_server((ELSEWHERE, int(port)))
    decoy.setblocking(False)
    answers = _resolving(monkeypatch, twin_host)
    data = tracker_cell().model_dump()
    data["robot"]["address"] = f"{NAME}:{port}"
    data["robot"]["poll_s"] = 0.002
    data["sensor"][0]["address"] = tracker.options.address
    config = config_from_dict(data, "test")
    stop = threading.Event()
    stop.set()  # connect, start, and stop before the first move
    try:
        outcome = start_campaign(
            config, str(tmp_path / "c.db"), config_path=None, mock=False, stop=stop
        )
        assert outcome.acquisition.interrupted and outcome.acquisition.stored == 0
        with pytest.raises(BlockingIOError):
            decoy.accept()  # nobody came
        assert answers == [twin_host]  # resolved once: for the claim
    finally:
        decoy.close()
