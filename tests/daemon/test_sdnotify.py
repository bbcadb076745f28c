"""sd_notify against a fake systemd: a datagram socket that receives what the service
sends, with the sender's pid from SO_PASSCRED, on a path and in the abstract namespace."""

from __future__ import annotations

import logging
import os
import uuid
from typing import Any

import pytest

from cellcal.service.sdnotify import Notifier

pytestmark = [pytest.mark.twin, pytest.mark.timeout(30)]


def test_ready_status_watchdog_stopping_reach_systemd(fake: tuple[Any, str]) -> None:
    systemd, path = fake
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled and n.watchdog_interval_s is None
    assert n.ready("idle; devices: robot ready, tracker connecting")
    fields, pid = systemd.receive()
    assert fields == {"READY": "1", "STATUS": "idle; devices: robot ready, tracker connecting"}
    assert pid == os.getpid()
    assert n.status("running campaign 3: pose 12 of 80 — 7 s dwell, σ 0.8 µm")
    assert systemd.receive()[0] == {
        "STATUS": "running campaign 3: pose 12 of 80 — 7 s dwell, σ 0.8 µm"
    }
    assert n.watchdog() and systemd.receive()[0] == {"WATCHDOG": "1"}
    assert n.status("line one\nline two") and systemd.receive()[0] == {
        "STATUS": "line one line two"
    }
    assert n.reloading()
    fields, _ = systemd.receive()
    assert fields["RELOADING"] == "1" and int(fields["MONOTONIC_USEC"]) > 0
    assert n.stopping("stopping: SIGTERM") and systemd.receive()[0] == {
        "STOPPING": "1",
        "STATUS": "stopping: SIGTERM",
    }
    assert systemd.nothing_waiting()


def test_abstract_socket_name(systemd_class: Any) -> None:
    name = f"cellcal-test-{uuid.uuid4().hex}"
    systemd = systemd_class("\0" + name)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert systemd.receive()[0] == {"READY": "1"}
    finally:
        systemd.sock.close()


def test_watchdog_interval_is_half_the_timeout_and_only_for_this_process() -> None:
    n = Notifier({"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "30000000"})
    assert n.watchdog_interval_s == 15.0
    mine = Notifier({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())})
    assert mine.watchdog_interval_s == 15.0
    other = Notifier({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_interval_s is None
    assert Notifier({"WATCHDOG_USEC": "x"}).watchdog_interval_s is None
    assert Notifier({"WATCHDOG_USEC": "0"}).watchdog_interval_s is None


def test_without_systemd_nothing_is_sent_and_a_gone_socket_never_raises() -> None:
    n = Notifier({})
    assert not n.enabled and not n.ready() and not n.watchdog()
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("cellcal.service.sdnotify")
    level = logger.level
    logger.setLevel(logging.WARNING)  # the CLI's tests leave the root logger at ERROR
    logger.addHandler(handler)
    try:
        gone = Notifier({"NOTIFY_SOCKET": "/tmp/cellcal-no-such-notify-socket"})
        assert not gone.ready() and not gone.status("x")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert len(records) == 1  # logged once, not per call
    assert records[0].getMessage().startswith("sd_notify to /tmp/cellcal-no-such-notify-socket")
