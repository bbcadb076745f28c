"""Debian's chromium driven through chromium-driver (selenium), for the pages' tests."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from typing import Any

import pytest

CHROMIUM = shutil.which("chromium")
CHROMEDRIVER = shutil.which("chromedriver")

needs_chromium = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="Debian's chromium and chromium-driver are not installed (make test installs them)",
)


def chromium(width: int, height: int) -> Any:
    """A headless browser with a window of this size (the caller quits it)."""
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service as DriverService

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]:
        options.add_argument(flag)
    options.add_argument("--disable-background-networking")
    options.add_argument(f"--window-size={width},{height}")
    return webdriver.Chrome(options=options, service=DriverService(str(CHROMEDRIVER)))


@pytest.fixture(scope="session")
def shared_chromium() -> Iterator[Any]:
    """One headless Chromium for every page test of the session (each test navigates it
    and sets its window size); started by the first test that asks, quit at the end."""
    browser = chromium(1280, 1500)
    browser.set_page_load_timeout(30)
    try:
        yield browser
    finally:
        browser.quit()
