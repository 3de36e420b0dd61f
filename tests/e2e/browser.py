"""A real headless Chromium for the dashboard's end-to-end tests (Debian's ``chromium``, driven by
playwright). The tests skip, with the reason, where either is missing."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
# No sandbox: the tests run as root in CI; the rest keeps Chromium off the network it has no business with.
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--no-first-run"]


# One Chromium per test module (started by the first test that needs it, closed by
# tests/e2e/conftest.py after the module): launching it costs seconds per test on a loaded machine, and every
# page gets a fresh context of its own anyway (browser.new_page), so tests share no cookies or storage.
_SHARED: dict = {}


@contextmanager
def headless_chromium() -> Iterator:
    """Yield the module's launched playwright ``Browser``; the pages (and their contexts) a test opened
    are closed afterwards, so the next test starts with none."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    browser = _SHARED.get("browser")
    if browser is None or not browser.is_connected():
        close_shared_browser()
        pw = sync_api.sync_playwright().start()
        _SHARED["pw"] = pw
        _SHARED["browser"] = browser = pw.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS)
    try:
        yield browser
    finally:
        for context in list(browser.contexts):
            context.close()


def close_shared_browser() -> None:
    browser, pw = _SHARED.pop("browser", None), _SHARED.pop("pw", None)
    try:
        if browser is not None and browser.is_connected():
            browser.close()
    finally:
        if pw is not None:
            pw.stop()


def open_dashboard(browser, url: str, *, fragment: str = "", on_response: Callable | None = None,
                   **page_options) -> tuple:
    """A page on ``url``/dashboard (``fragment`` after ``#``), once its map list has loaded; returns the page
    and the list the page's JavaScript errors are collected in. Handlers are in place before the first
    request, so ``on_response`` sees every response of the page."""
    page = browser.new_page(viewport={"width": 1440, "height": 1250}, **page_options)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    if on_response is not None:
        page.on("response", on_response)
    page.goto(f"{url}/dashboard" + (f"#{fragment}" if fragment else ""))
    page.wait_for_selector("#map-select option[value='demo-house']", state="attached", timeout=10_000)
    return page, errors
