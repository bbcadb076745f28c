"""A campaign's kind is shown (issue 30): ``cellcal campaign list`` (text and --json)
reads each campaign's kind from the database — a calibration (no ``kind`` event), an ISO
9283 test, one of an earlier cellcal (its ``iso9283`` event alone), and ``unknown`` for a
``kind`` event that does not read back as a name, never a refusal —; the control API's
status, the first status of its event stream and every status the stream sends after
carry the kind of the campaign shown (read once per campaign from the database).

The database is written through the store (no campaign runs); the API is served in this
process on a Unix socket in the test's folder."""

from __future__ import annotations

import asyncio
import json
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import web

from cellcal.campaign.kinds import KIND_EVENT, kind_record, shown_kinds
from cellcal.service.api import EventHub, make_app
from cellcal.service.control import Control
from cellcal.service.shown import campaign_view
from cellcal.store.database import Store
from tests.daemon.in_process import campaign_row, service_of
from tests.inprocess import cellcal

pytestmark = pytest.mark.timeout(60)

#: The campaigns written, by id, and the kind each is shown with.
EXPECTED = {1: "calibration", 2: "iso9283", 3: "iso9283", 4: "unknown", 5: "unknown"}


def _campaigns(db: Path) -> None:
    """Five complete campaigns: a calibration, an ISO 9283 test, one of an earlier
    cellcal, and two whose ``kind`` event does not read back as a kind's name."""
    store = Store(db)
    try:
        events: list[list[tuple[str, str]]] = [
            [],
            [(KIND_EVENT, kind_record("iso9283", {"cycles": 2})), ("iso9283", "2 cycles")],
            [("iso9283", "30 cycles, joints from model.toml")],
            [(KIND_EVENT, "{not json")],
            [(KIND_EVENT, kind_record("\x1b[31mdrift", {}))],
        ]
        for each in events:
            cid = campaign_row(store, status="complete")
            for kind, message in each:
                store.add_event(cid, kind, message)
    finally:
        store.close()


@pytest.fixture
def db(tmp_path: Path) -> Path:
    path = tmp_path / "kinds.db"
    _campaigns(path)
    return path


def test_the_campaign_list_shows_each_campaigns_kind(db: Path) -> None:
    run = cellcal("campaign", "list", "--db", db, "--json")
    assert run.returncode == 0, run.stderr
    rows = json.loads(run.stdout)["campaigns"]
    assert {r["id"]: r["kind"] for r in rows} == EXPECTED
    # the fields of before are all there still
    for key in ("created", "status", "model", "sensors", "n_poses", "poses_stored"):
        assert all(key in r for r in rows), key
    run = cellcal("campaign", "list", "--db", db)
    assert run.returncode == 0, run.stderr
    head, *lines = run.stdout.splitlines()
    assert head.split()[:5] == ["id", "created", "(UTC)", "status", "kind"]
    assert [line.split()[4] for line in lines] == list(EXPECTED.values())
    assert "\x1b" not in run.stdout
    store = Store(db, readonly=True)
    try:
        assert shown_kinds(store, 2) == {2: "iso9283"}
        assert shown_kinds(store, 1) == {}  # a calibration: no kind event
    finally:
        store.close()


@pytest.fixture
def short_folder() -> Iterator[Path]:
    # Unix socket paths are limited to 108 bytes: pytest's temp paths may be longer
    path = Path(tempfile.mkdtemp(prefix="cc-kind-", dir="/tmp"))
    yield path
    for p in path.iterdir():
        p.unlink()
    path.rmdir()


async def _next_status(lines: aiohttp.StreamReader) -> dict[str, Any]:
    """The data of the stream's next ``status`` event."""
    kind = ""
    async with asyncio.timeout(20):
        async for raw in lines:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "status":
                data: dict[str, Any] = json.loads(line[6:])
                return data
    raise AssertionError("the stream ended without a status")


async def _scenario(db: Path, folder: Path) -> None:
    sock = str(folder / "control.sock")
    store = Store(db)
    hub = EventHub()
    # as the service's: the control's statuses go out through the hub
    control = Control(["robot", "tracker"], hub.publish)
    svc = service_of(store, control, hub, sock)
    runner = web.AppRunner(make_app(svc))
    await runner.setup()
    try:
        await web.UnixSite(runner, sock).start()  # listening once started
        shown = campaign_view(store, 2)
        assert shown is not None
        control.show(*shown)  # an ISO 9283 test shown, as at start-up
        connector = aiohttp.UnixConnector(path=sock)
        async with aiohttp.ClientSession(connector=connector) as session:
            async with session.get("http://cellcal/v1/status") as resp:
                status = await resp.json()
            assert status["campaign"]["id"] == 2 and status["campaign"]["kind"] == "iso9283"
            async with session.get("http://cellcal/v1/events") as stream:
                first = await _next_status(stream.content)
                assert first["campaign"]["kind"] == "iso9283"
                # another campaign shown: the status the stream sends names its kind
                for cid in (1, 3):
                    view = campaign_view(store, cid)
                    assert view is not None
                    control.show(*view)
                    later = await _next_status(stream.content)
                    assert later["campaign"]["id"] == cid
                    assert later["campaign"]["kind"] == EXPECTED[cid]
            async with session.get("http://cellcal/v1/campaigns/3") as resp:
                assert (await resp.json())["kind"] == "iso9283"
        assert svc.kinds == {2: "iso9283", 1: "calibration", 3: "iso9283"}  # read once each
    finally:
        hub.close()  # as the service stops: each stream ends, so the site closes at once
        await runner.cleanup()
        store.close()


def test_the_status_and_its_stream_carry_the_kind_of_the_campaign_shown(
    db: Path, short_folder: Path
) -> None:
    asyncio.run(_scenario(db, short_folder))
