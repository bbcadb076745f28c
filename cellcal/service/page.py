"""The status page: a second, read-only site of the service on 127.0.0.1 (``--http``).

What it serves: three static files (``cellcal/data/status/``: the page, its plain
JavaScript and its style sheet) and, read-only, the control API's ``/v1/status`` and
``/v1/events``; the page follows the service through one EventSource. Nothing that
changes state listens on TCP: this site answers GET and HEAD only.

Defences (``specs``: the service): a ``Host`` header other than a loopback name or the
address bound is refused (a DNS-rebinding page cannot read it), no CORS headers, a
Content-Security-Policy that lets the page load nothing but its own files (cell PCs are
offline), and a bind to a non-loopback address only with an explicit option.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from importlib import resources
from typing import Any

from aiohttp import web

from cellcal.errors import InputError
from cellcal.service import api

#: The page's files: path → (file in cellcal/data/status, content type).
FILES = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/page.js": ("page.js", "text/javascript; charset=utf-8"),
    "/page.css": ("page.css", "text/css; charset=utf-8"),
}
HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
        "img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


@dataclass(frozen=True)
class HttpAddress:
    host: str  # an IP literal
    port: int

    @property
    def loopback(self) -> bool:
        return ipaddress.ip_address(self.host).is_loopback

    def url(self, port: int | None = None) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port if port is None else port}/"


def parse_http(value: str, allow_remote: bool = False) -> HttpAddress:
    """``HOST:PORT`` of ``--http``: an IP address (``localhost`` is 127.0.0.1) and a
    port (0: any free one); a non-loopback address only with ``allow_remote``."""
    host, sep, port_text = value.rpartition(":")
    if not sep or not host:
        raise InputError(f"--http {value}: give HOST:PORT, e.g. 127.0.0.1:8765")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if host == "localhost":
        host = "127.0.0.1"
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        raise InputError(f"--http {value}: {host!r} is not an IP address") from None
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise InputError(f"--http {value}: the port must be a number from 0 to 65535")
    if not ip.is_loopback and not allow_remote:
        raise InputError(
            f"--http {value}: not a loopback address; the status page is for this PC "
            "(add --http-allow-remote to serve it on the network, read-only)"
        )
    return HttpAddress(str(ip), port)


def host_allowed(header: str | None, bound: str) -> bool:
    """A ``Host`` header naming this PC: ``localhost`` (and ``*.localhost``), a
    loopback address, or the address bound (an IP literal cannot be rebound)."""
    if not header:
        return False
    name = header.strip().lower()
    if name.startswith("["):
        name = name[1 : name.find("]")] if "]" in name else ""
    elif name.count(":") == 1:
        name = name.partition(":")[0]
    if name == "localhost" or name.endswith(".localhost"):
        return True
    try:
        ip = ipaddress.ip_address(name)
    except ValueError:
        return False
    return ip.is_loopback or str(ip) == bound


def _refusal(status: int, message: str) -> web.Response:
    return web.Response(status=status, text=message + "\n", headers=HEADERS)


def _guard(bound: str) -> Any:
    @web.middleware
    async def guard(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method not in ("GET", "HEAD"):
            resp = _refusal(405, "the status page is read-only; cellcal campaign acts")
            resp.headers["Allow"] = "GET, HEAD"
            return resp
        if not host_allowed(request.headers.get("Host"), bound):
            host = request.headers.get("Host", "")
            return _refusal(403, f"Host {host!r} is not this PC's loopback name")
        try:
            response = await handler(request)
        except web.HTTPNotFound:
            return _refusal(404, f"no such page: {request.path}")
        response.headers.update(HEADERS)
        return response

    return guard


def _file(name: str, content_type: str) -> Handler:
    body = (resources.files("cellcal") / "data" / "status" / name).read_bytes()

    async def serve(request: web.Request) -> web.StreamResponse:
        return web.Response(body=body, headers={"Content-Type": content_type})

    return serve


async def _no_icon(request: web.Request) -> web.StreamResponse:
    return web.Response(status=204)


def make_page_app(svc: api.Service, bound: str) -> web.Application:
    app = web.Application(middlewares=[_guard(bound)])
    app[api.SERVICE] = svc
    for path, (name, content_type) in FILES.items():
        app.router.add_get(path, _file(name, content_type))
    app.router.add_get("/favicon.ico", _no_icon)
    app.router.add_get("/v1/status", api.status)
    app.router.add_get("/v1/events", api.events)
    return app
