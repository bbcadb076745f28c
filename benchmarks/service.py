"""Service benchmark: what the cell service costs — each figure against a peer measured in
this run, on this machine.

1. Control-API round trip: ``GET /v1/status`` on the service's Unix socket (aiohttp's
   client, one keep-alive connection) against ``GET`` on a bare aiohttp app that answers
   a fixed JSON of the same size, served the same way from a process of its own.
2. Event latency: from the moment the engine enters a phase of a pose (the status
   event's own ``phase_started``) to the event read by a watcher of ``/v1/events``,
   against a bare aiohttp server-sent-events stream that writes the time it sends.
3. Added cost per pose: the same mock campaign (``config/mock-cell-tracker.toml``,
   128 poses, simulated clock as fast as it goes, so that nothing hides the overhead)
   run by ``cellcal run`` and by the service: the process's CPU time from the first pose
   stored to the last, per pose (which the shared machine's load hardly moves), and the
   wall time per pose from the poses' stored times. Goal: the service adds under 5 %.
4. Idle CPU of the service with its devices connected (the twins are threads of it in
   mock mode), against the bare aiohttp app idle.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import aiohttp

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "config" / "mock-cell-tracker.toml"
POSES = 128  # the tracker cell's plan
CLI = [sys.executable, "-m", "cellcal"]


# ------------------------------------------------------------------ the bare peer


def serve_echo(sock: str, size: int) -> None:
    """The peer: a bare aiohttp app on a Unix socket (run as ``--echo SOCK SIZE``)."""
    from aiohttp import web

    body = json.dumps({"pad": "x" * max(0, size - 12)})

    async def status(request: web.Request) -> web.Response:
        return web.Response(text=body, content_type="application/json")

    async def events(request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream"})
        await resp.prepare(request)
        for i in range(400):
            data = json.dumps({"t": time.time(), "pad": "x" * 400})
            await resp.write(f"id: {i}\nevent: status\ndata: {data}\n\n".encode())
            await asyncio.sleep(0.01)
        return resp

    app = web.Application()
    app.router.add_get("/v1/status", status)
    app.router.add_get("/v1/events", events)
    web.run_app(app, path=sock, print=None, handle_signals=True)


# ------------------------------------------------------------------ clients


async def round_trips(sock: str, n: int) -> list[float]:
    async with aiohttp.ClientSession(connector=aiohttp.UnixConnector(path=sock)) as s:
        out = []
        for k in range(n + 20):
            t = time.perf_counter()
            async with s.get("http://cellcal/v1/status") as r:
                await r.read()
            if k >= 20:  # warm-up excluded
                out.append(time.perf_counter() - t)
        return out


async def event_latencies(sock: str, n: int, stamp: str, during: Any = None) -> list[float]:
    """Read ``n`` status events; the latency of each that carries its send time."""
    out: list[float] = []
    timeout = aiohttp.ClientTimeout(total=300)
    connector = aiohttp.UnixConnector(path=sock)
    session = aiohttp.ClientSession(connector=connector, timeout=timeout)
    async with session as s, s.get("http://cellcal/v1/events") as r:
        task = asyncio.create_task(during()) if during is not None else None
        kind = ""
        seen: set[float] = set()
        async for raw in r.content:
            now = time.time()
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "status":
                data = json.loads(line[6:])
                t = _stamp(data, stamp)
                if t is not None and t not in seen:  # each phase once
                    seen.add(t)
                    out.append(now - t)
                    if len(out) >= n:
                        break
        if task is not None:
            await task
    return out


def _stamp(data: dict[str, Any], stamp: str) -> float | None:
    if stamp == "t":
        return float(data["t"])
    c = data.get("campaign") or {}
    t = c.get("phase_started")
    return float(t) if t is not None and data.get("state") == "running" else None


# ------------------------------------------------------------------ processes


def wait_socket(sock: str, proc: subprocess.Popen[bytes], ready: bool) -> None:
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"the process serving {sock} ended ({proc.returncode})")
        if Path(sock).exists():
            if not ready:
                return
            status = asyncio.run(_get(sock, "/v1/status"))
            if all(d["state"] == "ready" for d in status["devices"].values()):
                return
        time.sleep(0.05)
    raise SystemExit(f"nothing answered on {sock}")


async def _get(sock: str, path: str) -> Any:
    session = aiohttp.ClientSession(connector=aiohttp.UnixConnector(path=sock))
    async with session as s, s.get(f"http://cellcal{path}") as r:
        return await r.json()


async def _post(sock: str, path: str, body: dict[str, Any]) -> Any:
    session = aiohttp.ClientSession(connector=aiohttp.UnixConnector(path=sock))
    async with session as s, s.post(f"http://cellcal{path}", json=body) as r:
        return await r.json()


def start_service(
    folder: Path, name: str, time_scale: float
) -> tuple[subprocess.Popen[bytes], str]:
    sock = str(folder / f"{name}.sock")
    cmd = [*CLI, "daemon", "--mock", "--config", str(CELL), "--db", str(folder / f"{name}.db")]
    cmd += ["--socket", sock, "--time-scale", str(time_scale)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_socket(sock, proc, ready=True)
    return proc, sock


def stop(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()


def per_pose(db: Path) -> tuple[float, int]:
    """Wall seconds per pose over the acquisition, from the poses' stored times (the
    samples' host times are the simulated clock's)."""
    with sqlite3.connect(db) as conn:
        times = [datetime.fromisoformat(t) for (t,) in conn.execute("SELECT stored FROM poses")]
    span = (max(times) - min(times)).total_seconds()
    return span / (len(times) - 1), len(times)


def _ticks(pid: int) -> int:
    """CPU clock ticks (user + system) the process has used, all its threads."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def cpu_per_pose(pid: int, db: Path, total: int) -> float:
    """CPU seconds the process ``pid`` spends per pose while it acquires: its ticks from
    the first pose stored to the last, read as the poses land in ``db`` (checked every
    2 ms). CPU time, unlike wall time, hardly moves with the shared machine's load."""
    deadline = time.monotonic() + 300
    while not db.exists():
        if time.monotonic() > deadline:
            raise SystemExit(f"{db} was not made")
        time.sleep(0.002)
    start: tuple[int, int] | None = None
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        while time.monotonic() < deadline:
            try:
                (n,) = conn.execute("SELECT COUNT(*) FROM poses").fetchone()
            except sqlite3.OperationalError:  # the schema is not there yet
                n = 0
            ticks = _ticks(pid)
            if start is None and n >= 1:
                start = (n, ticks)
            if start is not None and n >= total:
                return (ticks - start[1]) / os.sysconf("SC_CLK_TCK") / (n - start[0])
            time.sleep(0.002)
    raise SystemExit(f"{db}: the campaign did not end within 300 s")


@dataclass(frozen=True)
class Cost:
    """One campaign's cost per pose: wall seconds (stored times) and CPU seconds."""

    wall_s: float
    cpu_s: float
    poses: int


def campaign_by_run(folder: Path, k: int) -> Cost:
    db = folder / f"run{k}.db"
    cmd = [*CLI, "run", "--mock", "--config", str(CELL), "--db", str(db), "--time-scale", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cpu = cpu_per_pose(proc.pid, db, POSES)
    if proc.wait(120) != 0:
        raise SystemExit(f"cellcal run ended {proc.returncode}")
    wall, n = per_pose(db)
    return Cost(wall, cpu, n)


def campaign_by_service(folder: Path, k: int) -> tuple[Cost, subprocess.Popen[bytes]]:
    proc, sock = start_service(folder, f"svc{k}", 0.0)
    cid = asyncio.run(_post(sock, "/v1/campaigns", {"mock": True}))["campaign_id"]
    db = folder / f"svc{k}.db"
    cpu = cpu_per_pose(proc.pid, db, POSES)
    while True:
        with sqlite3.connect(db) as conn:
            (status,) = conn.execute("SELECT status FROM campaigns WHERE id = ?", (cid,)).fetchone()
        if status not in ("queued", "running"):
            break
        time.sleep(0.2)
    if status != "complete":
        raise SystemExit(f"the service's campaign ended {status}")
    wall, n = per_pose(db)
    return Cost(wall, cpu, n), proc


def cpu_percent(pid: int, seconds: float) -> float:
    t0, c0 = time.monotonic(), _ticks(pid)
    time.sleep(seconds)
    used = (_ticks(pid) - c0) / os.sysconf("SC_CLK_TCK")
    return 100.0 * used / (time.monotonic() - t0)


# ------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--echo", nargs=2, metavar=("SOCK", "SIZE"), help=argparse.SUPPRESS)
    p.add_argument("--trips", type=int, default=500)
    p.add_argument("--events", type=int, default=200)
    p.add_argument("--repeat", type=int, default=9)
    p.add_argument("--idle-s", type=float, default=10.0)
    args = p.parse_args(argv)
    if args.echo:
        serve_echo(args.echo[0], int(args.echo[1]))
        return 0
    with tempfile.TemporaryDirectory(prefix="cc-bench-", dir="/tmp") as tmp:
        folder = Path(tmp)
        service, sock = start_service(folder, "api", 0.01)
        size = len(json.dumps(asyncio.run(_get(sock, "/v1/status"))))
        peer_sock = str(folder / "echo.sock")
        echo_cmd = [sys.executable, __file__, "--echo", peer_sock, str(size)]
        echo = subprocess.Popen(echo_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            measure(args, folder, service, sock, echo, peer_sock, size)
        finally:
            if service.poll() is None:
                stop(service)
            echo.kill()
            echo.wait(10)
    return 0


def measure(
    args: argparse.Namespace,
    folder: Path,
    service: subprocess.Popen[bytes],
    sock: str,
    echo: subprocess.Popen[bytes],
    peer_sock: str,
    size: int,
) -> None:
    wait_socket(peer_sock, echo, ready=False)
    ours = statistics.median(asyncio.run(round_trips(sock, args.trips)))
    peer = statistics.median(asyncio.run(round_trips(peer_sock, args.trips)))
    print(f"== 1. Control-API round trip, GET /v1/status ({size} bytes), median of")
    print(f"   {args.trips}, one keep-alive connection on a Unix socket")
    print(f"   the service                                  {ours * 1e3:8.3f} ms")
    print(f"   a bare aiohttp app, same answer size (peer)  {peer * 1e3:8.3f} ms")
    print(f"   ratio {ours / peer:.2f}×")

    async def campaign() -> None:
        await _post(sock, "/v1/campaigns", {"mock": True})

    lat = asyncio.run(event_latencies(sock, args.events, "phase", campaign))
    lat_peer = asyncio.run(event_latencies(peer_sock, args.events, "t"))
    stop(service)
    ours, peer = statistics.median(lat), statistics.median(lat_peer)
    p95 = sorted(lat)[int(0.95 * len(lat))]
    print(f"== 2. Event latency, engine phase → watcher of /v1/events, median of {len(lat)}")
    print(f"   the service (engine thread → loop → SSE)     {ours * 1e3:8.3f} ms")
    print(f"   a bare aiohttp SSE stream (peer)             {peer * 1e3:8.3f} ms")
    print(f"   ratio {ours / peer:.2f}×   (95th percentile of the service {p95 * 1e3:.2f} ms)")

    runs: list[Cost] = []
    svcs: list[Cost] = []
    for k in range(args.repeat):
        # Each pair back to back, nothing else of ours running, the order alternating so
        # that a drift of the shared machine's speed does not fall on one side.
        for side in ("run", "service") if k % 2 == 0 else ("service", "run"):
            if side == "run":
                runs.append(campaign_by_run(folder, k))
            else:
                cost, proc = campaign_by_service(folder, k)
                stop(proc)
                svcs.append(cost)
    pairs = list(zip(svcs, runs, strict=True))
    # Each pair ran back to back: the median of the pairs' ratios is the steadier figure.
    wall = 100.0 * (statistics.median(s.wall_s / r.wall_s for s, r in pairs) - 1)
    cpu = 100.0 * (statistics.median(s.cpu_s / r.cpu_s for s, r in pairs) - 1)
    print(f"== 3. Cost per pose, the tracker cell's campaign ({runs[0].poses} poses), simulated")
    print(f"   clock as fast as it goes; {args.repeat} pairs back to back, order alternating;")
    print("   medians of the pairs (the process's CPU from the first pose stored to the last)")
    print(
        f"   the service        wall {statistics.median(s.wall_s for s in svcs) * 1e3:6.2f} ms"
        f"   CPU {statistics.median(s.cpu_s for s in svcs) * 1e3:6.2f} ms per pose"
    )
    print(
        f"   cellcal run (peer) wall {statistics.median(r.wall_s for r in runs) * 1e3:6.2f} ms"
        f"   CPU {statistics.median(r.cpu_s for r in runs) * 1e3:6.2f} ms per pose"
    )
    spread = ", ".join(f"{100 * (s.cpu_s / r.cpu_s - 1):+.1f}" for s, r in pairs)
    print(f"   the service adds {cpu:+.1f} % CPU per pose ({spread} %)")
    spread = ", ".join(f"{100 * (s.wall_s / r.wall_s - 1):+.1f}" for s, r in pairs)
    print(f"   and {wall:+.1f} % wall time per pose ({spread} %)")
    verdict = "met" if cpu < 5.0 else "NOT met"
    print(f"   goal < 5 % (CPU): {verdict}")
    proc, _ = start_service(folder, "idle", 0.0)  # devices connected, nothing queued
    try:
        time.sleep(2.0)
        cpu_ours = cpu_percent(proc.pid, args.idle_s)
        cpu_peer = cpu_percent(echo.pid, args.idle_s)
    finally:
        stop(proc)
    print(f"== 4. Idle CPU over {args.idle_s:.0f} s, devices connected (twins in-process)")
    print(f"   the service                                  {cpu_ours:8.2f} % of a core")
    print(f"   a bare aiohttp app idle (peer)               {cpu_peer:8.2f} % of a core")


if __name__ == "__main__":
    sys.exit(main())
