"""The status page: ``--http`` refusals, the read-only site's defences (GET only, Host
header, no CORS, nothing from outside) against the service as a subprocess, and the
page itself in headless Chromium (Debian's chromium + chromium-driver) following a mock
campaign to its validation errors, with screenshots."""

from __future__ import annotations

import http.client
import random
import re
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cellcal.commands.service_client import call
from cellcal.errors import InputError
from cellcal.service.page import FILES, host_allowed, parse_http
from tests.browser import needs_chromium
from tests.daemon.conftest import small_cell

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "cellcal" / "data" / "status"
TRACKER_CELL = ROOT / "config" / "mock-cell-tracker.toml"

pytestmark = [pytest.mark.twin, pytest.mark.slow, pytest.mark.browser, pytest.mark.timeout(240)]


def test_http_address_is_loopback_unless_allowed() -> None:
    assert parse_http("127.0.0.1:8765").host == "127.0.0.1"
    assert parse_http("localhost:0").host == "127.0.0.1"
    assert parse_http("[::1]:80").url() == "http://[::1]:80/"
    for bad, words in [
        ("8765", "HOST:PORT"),
        ("cell-pc:8765", "not an IP address"),
        ("127.0.0.1:http", "0 to 65535"),
        ("127.0.0.1:70000", "0 to 65535"),
        ("0.0.0.0:8765", "--http-allow-remote"),
        ("192.168.0.10:8765", "not a loopback address"),
    ]:
        with pytest.raises(InputError, match=words):
            parse_http(bad)
    assert not parse_http("192.168.0.10:8765", allow_remote=True).loopback


def test_host_header_must_name_this_pc() -> None:
    for ok in ["127.0.0.1:8765", "localhost:8765", "LOCALHOST", "cell.localhost:1", "[::1]:80"]:
        assert host_allowed(ok, "127.0.0.1"), ok
    assert host_allowed("127.9.9.9:1", "127.0.0.1")  # all of 127/8 is loopback
    assert host_allowed("192.168.0.10:8765", "192.168.0.10")  # the address bound
    for bad in [None, "", "evil.example:8765", "192.168.0.10:8765", "localhost.evil.example"]:
        assert not host_allowed(bad, "127.0.0.1"), bad


def test_the_page_loads_nothing_from_outside() -> None:
    """Cell PCs are offline: no URL but the SVG namespace's name, no import, no inline
    script (the Content-Security-Policy forbids it)."""
    for _, (name, _) in FILES.items():
        text = (STATIC / name).read_text()
        urls = set(re.findall(r"https?://[^\s\"')]+", text)) - {"http://www.w3.org/2000/svg"}
        assert not urls, (name, urls)
        assert "@import" not in text and "url(" not in text, name
    html = (STATIC / "index.html").read_text()
    assert re.findall(r"<script[^>]*>", html) == ['<script src="page.js" defer>']
    assert "style=" not in html


def _address() -> str:
    """A loopback address of 127.0.0.x (port 0 takes a free port on it)."""
    return f"127.0.0.{random.randint(2, 254)}"


def _get(url: str, path: str, method: str = "GET", **headers: str) -> http.client.HTTPResponse:
    host, port = url.removeprefix("http://").rstrip("/").rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port), timeout=10)
    conn.request(method, path, headers=headers)
    resp = conn.getresponse()
    resp.read()
    conn.close()
    return resp


def _page_url(d: Any) -> str:
    url = call(d.sock, "GET", "/v1/info")["http"]
    assert isinstance(url, str) and url.startswith("http://127.")
    return url


def test_the_page_site_is_read_only(folder: Path, daemon: Callable[..., Any]) -> None:
    d = daemon(folder, None, 0.02, ["--http", f"{_address()}:0"])
    d.start()
    url = _page_url(d)
    host = url.removeprefix("http://").rstrip("/")
    ok = _get(url, "/", Host=host, Origin="http://evil.example")
    assert ok.status == 200
    assert "default-src 'none'" in ok.headers["Content-Security-Policy"]
    assert not [h for h in ok.headers if h.lower().startswith("access-control-")]
    assert _get(url, "/page.js", Host="localhost").status == 200
    assert _get(url, "/v1/status", Host=host).status == 200
    rebound = _get(url, "/v1/status", Host="evil.example:8765")
    assert rebound.status == 403
    for method, path in [("POST", "/v1/campaigns"), ("POST", "/v1/campaigns/current/abort")]:
        refused = _get(url, path, method, Host=host)
        assert refused.status == 405 and refused.headers["Allow"] == "GET, HEAD"
    for path in ["/v1/campaigns", "/v1/info", "/../../etc/passwd"]:
        assert _get(url, path, Host=host).status == 404, path
    assert d.rows("SELECT COUNT(*) FROM campaigns")[0][0] == 0
    assert d.stop() == 0


def _short_campaign() -> str:
    """The tracker cell's configuration with a smaller plan (the service's [robot] and
    [sensor] unchanged): 36 calibration poses and 8 + 5×2 validation poses."""
    text = TRACKER_CELL.read_text()
    text = text.replace("grid = [4, 4, 5]", "grid = [3, 3, 4]")
    text = text.replace("validation_inside = 20", "validation_inside = 8")
    return text.replace("validation_per_region = 6", "validation_per_region = 2")


def _cells(browser: Any, rows: str, cells: str = "td") -> list[list[str]]:
    """The text of each row's cells, read in one script: a page that redraws a table
    between reading a row and reading its cells leaves no stale element to fail on."""
    out: list[list[str]] = browser.execute_script(
        "return Array.from(document.querySelectorAll(arguments[0])).map(r =>"
        " Array.from(r.querySelectorAll(arguments[1])).map(c => c.innerText.trim()))",
        rows,
        cells,
    )
    return out


@needs_chromium
def test_the_page_in_chromium_follows_a_campaign_to_its_errors(
    folder: Path,
    daemon: Callable[..., Any],
    capsys: pytest.CaptureFixture[str],
    shared_chromium: Any,
) -> None:
    d = daemon(folder, None, 0.03, ["--http", f"{_address()}:0"], config=small_cell(folder))
    d.start()
    url = _page_url(d)
    browser = shared_chromium
    browser.set_window_size(1280, 1500)
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    shots = []
    browser.get(url)
    wait = WebDriverWait(browser, 90, poll_frequency=0.1)
    text = lambda i: browser.find_element(By.ID, i).text  # noqa: E731
    wait.until(lambda _: text("link") == "live" and text("state") == "IDLE")
    assert "cellcal campaign start" in text("command")
    started = call(
        d.sock,
        "POST",
        "/v1/campaigns",
        {"config_toml": _short_campaign(), "config_name": str(TRACKER_CELL), "mock": True},
    )
    cid, planned = started["campaign_id"], started["n_poses"]
    progress = re.compile(rf"pose (\d+) of {planned}$")

    def stored(_: Any) -> bool:
        m = progress.match(text("progress"))
        return text("state") == "RUNNING" and m is not None and int(m.group(1)) >= 3

    wait.until(stored)
    assert "cellcal campaign pause" in text("command")
    assert text("phase").startswith("phase: pose ")
    assert "calibration" in text("roles") and "validation" in text("roles")
    assert text("campaign-id") == str(cid)
    assert text("campaign-kind") == "calibration"
    shots.append(folder / "status-page-running.png")
    browser.save_screenshot(str(shots[-1]))
    # read at once: the running page replaces its rows with every pose stored
    rows = _cells(browser, "#poses tbody tr")
    assert rows and rows[0][0].isdigit()
    assert browser.find_elements(By.CSS_SELECTOR, "#plot polyline")
    assert [r[0] for r in _cells(browser, "#sensors tbody tr")] == ["tracker"]

    wait.until(lambda _: browser.find_element(By.ID, "end-box").is_displayed())
    wait.until(lambda _: text("state") == "IDLE")
    shots.append(folder / "status-page-complete.png")
    browser.save_screenshot(str(shots[-1]))
    assert text("progress") == f"pose {planned} of {planned}"
    cells = _cells(browser, "#end tbody tr", "th, td")
    summary = call(d.sock, "GET", f"/v1/campaigns/{cid}")
    assert summary["status"] == "complete"
    assert cells[0][:2] == ["before calibration", f"{summary['rms_before_mm']:.4f}"]
    assert cells[1][:2] == ["after calibration", f"{summary['rms_after_mm']:.4f}"]
    assert text("end-message").startswith("complete: RMS ")
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors
    assert d.stop() == 0
    deadline = time.monotonic() + 30
    while text("link") == "live" and time.monotonic() < deadline:
        time.sleep(0.1)
    assert text("link").startswith("unreachable")
    assert text("command") == "systemctl status cellcal"
    kept = Path(ROOT / ".pytest_cache" / "status-page")
    kept.mkdir(parents=True, exist_ok=True)
    with capsys.disabled():
        for shot in shots:
            shutil.copy(shot, kept / shot.name)
            print(f"\n  status page screenshot: {kept / shot.name}")


def _start(d: Any, seed: int) -> int:
    body = {"config_toml": _short_campaign(), "config_name": str(TRACKER_CELL), "mock": True}
    cid = call(d.sock, "POST", "/v1/campaigns", body | {"seed": seed})["campaign_id"]
    assert isinstance(cid, int)
    return cid


@needs_chromium
def test_the_page_shows_one_campaign_its_poses_and_a_keyed_plot(
    folder: Path,
    daemon: Callable[..., Any],
    capsys: pytest.CaptureFixture[str],
    shared_chromium: Any,
) -> None:
    """Campaign A aborted, B paused: the page loaded then names B in its headings, lists
    and plots B's poses alone, and keys its plot; after a restart it shows B, held,
    with the command that resumes it."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    d = daemon(folder, None, 0.02, ["--http", f"{_address()}:0"])
    d.start()
    a = _start(d, 1)
    d.until(lambda s: s["state"] == "running" and s["campaign"]["stored"] >= 6)
    call(d.sock, "POST", "/v1/campaigns/current/abort", {})
    d.until(lambda s: s["state"] == "idle" and "aborted" in s["reason"])
    b = _start(d, 2)
    d.until(lambda s: s["state"] == "running" and s["campaign"]["stored"] >= 3)
    call(d.sock, "POST", "/v1/campaigns/current/pause", {})
    d.until(lambda s: s["state"] == "paused")
    stored_b = [i for (i,) in d.rows(f"SELECT idx FROM poses WHERE campaign_id = {b} ORDER BY id")]
    assert d.rows(f"SELECT COUNT(*) FROM poses WHERE campaign_id = {a}")[0][0] >= 6

    browser = shared_chromium
    browser.set_window_size(1280, 1700)
    browser.get_log("browser")  # what an earlier test left
    wait = WebDriverWait(browser, 60, poll_frequency=0.1)
    text = lambda i: browser.find_element(By.ID, i).text  # noqa: E731

    def rows() -> list[Any]:
        return browser.find_elements(By.CSS_SELECTOR, "#poses tbody tr")

    def check_page(status: str) -> None:
        wait.until(
            lambda _: text("link") == "live" and text("campaign-id") == str(b),
            f"the page never showed campaign {b}",
        )
        wait.until(
            lambda _: len(rows()) == len(stored_b),
            f"campaign {b} stored {len(stored_b)} poses; the page did not list them alone",
        )
        assert text("campaign-status") == status
        assert f"campaign {b}" in text("poses-title")
        assert f"campaign {b}" in text("plot-title")
        assert f"campaign {b}, pose {stored_b[-1]}" in text("sensors-title")
        shown = rows()
        assert {r.get_attribute("data-campaign") for r in shown} == {str(b)}
        assert [int(r.find_elements(By.TAG_NAME, "td")[0].text) for r in shown] == stored_b[::-1]
        assert len(browser.find_elements(By.CSS_SELECTOR, "#plot > circle")) == len(stored_b)
        legend = [t.text for t in browser.find_elements(By.CSS_SELECTOR, "#plot g.legend text")]
        assert legend == ["tracker: 3-D σ (µm)", "time per pose (s)"]
        assert "3-D norm √(σx² + σy² + σz²)" in text("plot-key")
        assert "cellcal campaign watch" in text("plot-key")
        # the σ listed is the service's (the last pose's, in µm)
        last = call(d.sock, "GET", "/v1/status")["recent_poses"][-1]
        sigma = 1000 * last["sensors"]["tracker"]["sigma_mm"]
        assert shown[0].find_elements(By.TAG_NAME, "td")[-1].text == f"{sigma:.1f}"
        assert not browser.find_element(By.ID, "end-box").is_displayed()  # A's end is not B's
        assert f"cellcal campaign resume {b}" in text("held")
        errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors

    browser.get(_page_url(d))
    check_page("paused")
    shots = [folder / "status-page-one-campaign.png"]
    browser.save_screenshot(str(shots[-1]))

    # A restart: the held campaign is still the page's, with what to do. The page is
    # left first: an open page retries its event stream while the service is down, and
    # that refused connection is the restart's, not an error of the page after it.
    browser.get("about:blank")
    browser.get_log("browser")
    assert d.stop() == 0
    d.start()
    browser.get(_page_url(d))
    check_page("interrupted")
    assert text("state") == "PAUSED"
    assert f"cellcal campaign resume {b}" in text("command")
    assert f"{len(stored_b)} of " in text("held") and "interrupted" in text("held")
    shots.append(folder / "status-page-after-restart.png")
    browser.save_screenshot(str(shots[-1]))
    assert d.stop() == 0
    kept = Path(ROOT / ".pytest_cache" / "status-page")
    kept.mkdir(parents=True, exist_ok=True)
    with capsys.disabled():
        for shot in shots:
            shutil.copy(shot, kept / shot.name)
            print(f"\n  status page screenshot: {kept / shot.name}")
