"""The rig's camera twin runs in a child process of the campaign's, in the terminal's
foreground process group: a Ctrl-C reaches it too. It ignores SIGINT from its first
instruction to its last, keeps serving, and ends when its parent stops it."""

from __future__ import annotations

import multiprocessing.context
import os
import signal
import threading
from typing import Any

import pytest

from cellcal.commands.mock import simulated_cell_of
from cellcal.mocks.netns import NamespaceUnavailableError
from cellcal.mocks.rig.process import serve_in_process
from cellcal.mocks.rig.twin import RigTruth
from tests.e2e.rig_cell import gige_or_skip

pytestmark = [pytest.mark.twin, pytest.mark.timeout(120)]


def _start() -> Any:
    config, cell = simulated_cell_of(None, 3)
    sensor = next(s for s in config.sensor if s.kind == "photogrammetry")
    try:
        return serve_in_process(sensor, RigTruth.of(cell, sensor.name), cell).server
    except NamespaceUnavailableError as exc:
        pytest.skip(str(exc))


def _serves(child: Any) -> None:
    """A round trip through the child's loop: it is alive and answering."""
    child.stop_camera("cam3")


def test_the_camera_process_ignores_sigint_and_is_stopped_by_its_parent(capfd):
    gige_or_skip()
    child = _start()
    try:
        for _ in range(3):
            os.kill(child.process.pid, signal.SIGINT)
        _serves(child)
        assert child.process.is_alive()
    finally:
        child.stop()
    assert child.process.exitcode == 0
    assert "KeyboardInterrupt" not in capfd.readouterr().err


def test_a_sigint_while_the_camera_process_starts_is_dropped(monkeypatch, capfd):
    """SIGINT again and again from the moment the child exists until it serves: while
    it imports and opens its cameras it holds SIGINT blocked, then drops it."""
    gige_or_skip()
    started: list[Any] = []
    original = multiprocessing.context.SpawnProcess.start

    def start(self: Any) -> None:
        original(self)
        started.append(self)

    monkeypatch.setattr(multiprocessing.context.SpawnProcess, "start", start)
    done = threading.Event()
    sent = {"n": 0}

    def interrupt() -> None:
        while not done.is_set():
            if started and started[0].pid is not None:
                os.kill(started[0].pid, signal.SIGINT)
                sent["n"] += 1
            done.wait(0.002)

    pest = threading.Thread(target=interrupt, daemon=True)
    pest.start()
    try:
        child = _start()
    finally:
        done.set()
        pest.join(10)
    try:
        assert sent["n"] > 0
        _serves(child)
    finally:
        child.stop()
    assert child.process.exitcode == 0
    assert "KeyboardInterrupt" not in capfd.readouterr().err
