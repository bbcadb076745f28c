"""``cellcal campaign ...``: start, control and watch the service's campaigns; ``list``
also reads a database file directly (``--db``)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import click

from cellcal.campaign.kinds import kind_named
from cellcal.commands.output import SEED, print_json
from cellcal.commands.run import kind_options, other_kind_asked
from cellcal.commands.service_client import answer_of, call, follow, one_line, socket_path
from cellcal.errors import InputError, UserError
from cellcal.reports.folder import list_campaigns
from cellcal.store.database import Store

EXIT_REFUSED = 3
EXIT_FAILED = 2

SOCKET = click.option(
    "--socket",
    "sock",
    help="The service's control socket (default: $CELLCAL_SOCKET, else /run/cellcal/control.sock).",
)
JSON = click.option("--json", "as_json", is_flag=True, help="Print JSON on stdout.")


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.4f}"


def _kind(campaign: dict[str, Any]) -> str:
    """A campaign's kind as the service or the database says it (— from a service of an
    earlier cellcal, which does not), in one short line."""
    return one_line(campaign.get("kind") or "—", 40)


@click.group()
def campaign() -> None:
    """Start, control and watch campaigns in the cell service; list a database's."""


@campaign.command("list")
@click.option("--db", "db_path", help="Read this campaign database instead of asking the service.")
@SOCKET
@JSON
def list_command(db_path: str | None, sock: str | None, as_json: bool) -> None:
    """Campaigns with status, poses stored and result."""
    if db_path is not None:
        store = Store(db_path, readonly=True)
        try:
            rows = [r.as_dict() for r in list_campaigns(store)]
        finally:
            store.close()
        source = db_path
    else:
        path = socket_path(sock)
        try:
            answer = call(path, "GET", "/v1/campaigns?limit=1000")
            with answer_of(path, "list of campaigns"):
                rows = answer["campaigns"]
                if not isinstance(rows, list):
                    raise TypeError("campaigns is not a list")
        except UserError as exc:
            raise UserError(f"{exc}; or read a database file with --db FILE") from None
        source = path
    if as_json:
        print_json({"database" if db_path else "socket": source, "campaigns": rows})
        return
    lines = [
        f"{'id':>4}  {'created (UTC)':<19} {'status':<12} {'kind':<12} {'poses':>11}  "
        f"{'RMS before':>11}  {'RMS after':>10}  model / sensors"
    ]
    with answer_of(source, "list of campaigns"):
        for r in rows:
            created = r["created"][:19].replace("T", " ")
            lines.append(
                f"{r['id']:>4}  {created:<19} {r['status']:<12} {_kind(r):<12} "
                f"{r['poses_stored']:>5} / {r['n_poses']:<4} {_fmt(r['rms_before_mm']):>11}  "
                f"{_fmt(r['rms_after_mm']):>10}  {r['model']} / {', '.join(r['sensors'])}"
            )
    for line in lines:
        click.echo(line)


@campaign.command("start")
@click.option("--config", "config_path", help="Cell configuration (TOML) sent to the service.")
@click.option("--mock", is_flag=True, help="The service's simulated cell (a --mock service).")
@click.option("--seed", type=SEED, help="Mock mode: the plan's seed.")
@click.option("--queue", is_flag=True, help="Queue it behind the campaign that runs.")
@kind_options(sent=True)
@SOCKET
@JSON
def start(
    config_path: str | None,
    mock: bool,
    seed: int | None,
    queue: bool,
    kind: str,
    sock: str | None,
    as_json: bool,
    **given: Any,
) -> None:
    """Ask the service to run a campaign (with this configuration's text, or its own) of
    a kind: a calibration, or an ISO 9283 test (--kind iso9283 --model FILE)."""
    body: dict[str, Any] = {"when": "queue" if queue else "now", "seed": seed}
    what = ""
    if other_kind_asked(kind, given):
        # The options as the service takes them: a file they name is read here, sent.
        body["kind"] = kind
        body["options"] = kind_named(kind).read_options(given)
        what = f"{kind_named(kind).title}, " if kind != "calibration" else ""
    if mock:
        body["mock"] = True
    if config_path is not None:
        p = Path(config_path)
        try:
            body["config_toml"] = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{config_path}: cannot read ({exc})") from None
        # The file's real path goes with its text: the service takes the relative paths
        # in it (rig_file, target_file, a robot model file) against this file's folder,
        # as load_config does for the service's own file, so the very file the service
        # runs compares equal from any working folder.
        body["config_name"] = str(p.resolve())
    path = socket_path(sock)
    answer = call(path, "POST", "/v1/campaigns", body)
    if as_json:
        print_json(answer)
        return
    with answer_of(path, "answer to a start"):
        cid, n_poses = int(answer["campaign_id"]), int(answer["n_poses"])
    click.echo(
        f"campaign {cid} {'queued' if queue else 'accepted'} ({what}{n_poses} poses); "
        f"watch it: cellcal campaign watch {cid}"
    )


@campaign.command("status")
@SOCKET
@JSON
def status(sock: str | None, as_json: bool) -> None:
    """The service's state, its campaign's progress, the devices and the queue."""
    path = socket_path(sock)
    snap = call(path, "GET", "/v1/status")
    if as_json:
        print_json(snap)
        return
    with answer_of(path, "status"):
        lines = _status_lines(snap)
    for line in lines:
        click.echo(line)


def _status_lines(snap: dict[str, Any]) -> list[str]:
    """What ``campaign status`` prints (a status not shaped as the service's raises)."""
    lines = [f"{snap['state']}: {snap['reason']}"]
    c = snap.get("campaign")  # the running one, else the one held, else the last one
    if c:
        # a countdown only while the campaign goes on (not pausing, paused or aborting)
        going = snap["state"] == "running" and c.get("status") != "paused"
        eta = c.get("eta_s") if going else None
        status = f" ({c['status']})" if c.get("status") else ""
        kind = f"{_kind(c)} " if c.get("kind") else ""
        lines.append(
            f"{kind}campaign {c['id']}{status}: {c.get('stored', 0)} of {c.get('planned', 0)} "
            f"poses stored, phase {c.get('phase')}" + (f", about {eta:.0f} s to go" if eta else "")
        )
    devices = ", ".join(f"{k} {v['state']}" for k, v in snap["devices"].items())
    lines.append(f"devices: {devices}")
    fleet = snap.get("fleet")
    if fleet:
        error = f"; last error: {fleet['last_error']}" if fleet.get("last_error") else ""
        lines.append(
            f"fleet: {fleet['waiting']} waiting, last sent {fleet.get('last_sent') or 'never'}"
            + error
        )
    queue = snap.get("queue") or []
    lines.append(f"queue: {', '.join(map(str, queue)) if queue else 'empty'}")
    if snap.get("paused_campaign") is not None:
        cid = snap["paused_campaign"]
        lines.append(
            f"to go on: cellcal campaign resume {cid}; to drop it: cellcal campaign abort {cid}"
        )
    return lines


def _act(
    sock: str | None, campaign_id: int | None, action: str, body: dict[str, Any]
) -> dict[str, Any]:
    """The service's answer to a pause, resume or abort: its ``campaign_id`` and ``state``."""
    which = "current" if campaign_id is None else str(campaign_id)
    path = socket_path(sock)
    answer = call(path, "POST", f"/v1/campaigns/{which}/{action}", body)
    with answer_of(path, f"answer to {action}"):
        cid, state = answer["campaign_id"], answer["state"]
        number = cid is None or (isinstance(cid, int) and not isinstance(cid, bool))
        if not number or not isinstance(state, str):
            raise TypeError(f"campaign_id {cid!r}, state {state!r}")
    return dict(answer)


@campaign.command("pause")
@click.option("--now", is_flag=True, help="Abandon the pose under way (redone in full on resume).")
@SOCKET
@JSON
def pause(now: bool, sock: str | None, as_json: bool) -> None:
    """Pause the running campaign after the pose under way (or at once with --now)."""
    answer = _act(sock, None, "pause", {"mode": "immediate" if now else "deferred"})
    if as_json:
        print_json(answer)
    else:
        when = "now" if now else "after the pose under way"
        click.echo(f"campaign {answer['campaign_id']}: pausing {when}")


@campaign.command("resume")
@click.argument("campaign_id", type=int, required=False)
@SOCKET
@JSON
def resume(campaign_id: int | None, sock: str | None, as_json: bool) -> None:
    """Go on with the paused (or an interrupted) campaign: every pose exactly once."""
    answer = _act(sock, campaign_id, "resume", {})
    if as_json:
        print_json(answer)
    else:
        click.echo(f"campaign {answer['campaign_id']}: resuming")


@campaign.command("abort")
@click.argument("campaign_id", type=int, required=False)
@SOCKET
@JSON
def abort(campaign_id: int | None, sock: str | None, as_json: bool) -> None:
    """Abort the running campaign (robot stopped at once), or a paused or queued one."""
    answer = _act(sock, campaign_id, "abort", {})
    if as_json:
        print_json(answer)
    else:
        click.echo(f"campaign {answer['campaign_id']}: {answer['state']}")


@campaign.command("watch")
@click.argument("campaign_id", type=int, required=False)
@SOCKET
@click.option("--json", "as_json", is_flag=True, help="One JSON event per line (NDJSON).")
def watch(campaign_id: int | None, sock: str | None, as_json: bool) -> int:
    """Follow a campaign live until it ends (default: the current one)."""
    path = socket_path(sock)
    target: dict[str, int | None] = {"id": campaign_id}
    ended: dict[str, str] = {}
    shown = {"state": ""}

    def handle(event_id: int, kind: str, data: Any) -> bool:
        with answer_of(path, f"event {event_id} ({kind})"):
            return _handle(event_id, kind, data)

    def _handle(event_id: int, kind: str, data: Any) -> bool:
        if not isinstance(data, dict):
            raise TypeError(f"a JSON {type(data).__name__}, not an object")
        running = data.get("state") in ("running", "pausing", "aborting", "analysing")
        if kind == "status" and target["id"] is None and data.get("campaign") and running:
            target["id"] = int(data["campaign"]["id"])
        mine = target["id"] is None or data.get("campaign_id") in (None, target["id"])
        if as_json:
            if mine:
                click.echo(_line({"id": event_id, "event": kind, "data": data}))
        elif kind == "status":
            line = f"{data['state']}: {data['reason']}"
            if line != shown["state"]:
                shown["state"] = line
                _show(kind, data)
        elif mine:
            _show(kind, data)
        if kind == "campaign-end" and data.get("campaign_id") == target["id"]:
            ended["status"] = data["status"]
            return True
        return False

    if not follow(path, handle):
        click.echo("the service closed the event stream (stopped?)", err=True)
        return 0
    # refused by an acceptance check: 3, as cellcal run; failed (it could not start): 2
    return {"refused": EXIT_REFUSED, "failed": EXIT_FAILED}.get(ended.get("status", ""), 0)


def _sigma(s: dict[str, Any]) -> str:
    """A sensor's σ at a pose as the status page shows it: the service's ``sigma_mm``, the
    3-D norm √(σx² + σy² + σz²) of the per-axis standard deviations (computed here from
    ``std_mm`` for a service that does not send it)."""
    v = s.get("sigma_mm") if "sigma_mm" in s else math.hypot(*s["std_mm"])
    return "—" if v is None or not math.isfinite(v) else f"{v:.4f} mm"


def _line(obj: Any) -> str:
    import json

    return json.dumps(obj, separators=(",", ":"))


def _show(kind: str, data: dict[str, Any]) -> None:
    if kind == "status":
        c = data.get("campaign") or {}
        progress = f" [{c.get('stored', 0)}/{c.get('planned', 0)}]" if c else ""
        click.echo(f"{data['state']}{progress}: {data['reason']}")
    elif kind == "pose":
        sigma = ", ".join(f"{name} 3-D σ {_sigma(s)}" for name, s in data["sensors"].items())
        click.echo(
            f"pose {data['stored']}/{data['planned']} stored ({data['role']}, {data['region']}; "
            f"{sigma})"
        )
    elif kind == "event":
        click.echo(f"{data['kind']}: {data['message']}")
    elif kind == "campaign-end":
        v = data.get("validation_mm")
        tail = ""
        if v:
            tail = (
                f"; validation RMS {v['before']['rms']:.4f} → {v['after']['rms']:.4f} mm "
                f"({v['improvement_pct']:.1f} % reduction)"
            )
        click.echo(f"campaign {data['campaign_id']} {data['status']}: {data['message']}{tail}")
    sys.stdout.flush()
