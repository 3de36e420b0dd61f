"""A real headless Chromium for the dashboard's end-to-end tests (Debian's ``chromium``, driven by
playwright from a thread of its own, one browser per session). The tests skip, with the reason, where
either is missing."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
# No sandbox: the tests run as root in CI; the rest keeps Chromium off the network it has no business with.
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--no-first-run"]


class _PlaywrightThread:
    """One thread that owns playwright: every call into it runs there, one at a time.

    Playwright's sync API keeps its event loop marked as running in the thread that started it for as long
    as it lives (between calls too), so in that thread every later ``asyncio.run`` (the gateway's stream
    tests) fails with "cannot be called from a running event loop". Owned by a thread of its own, the
    browser can live for the whole session: the test's thread never sees that loop."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name="playwright", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while (job := self._jobs.get()) is not None:
            fn, done = job
            if done.set_running_or_notify_cancel():
                try:
                    done.set_result(fn())
                except BaseException as exc:  # noqa: BLE001  (handed to the caller, raised there)
                    done.set_exception(exc)

    def call(self, fn: Callable[[], Any]) -> Any:
        # Handlers a test registered (page.on) run in this thread, inside a call: they call straight in.
        if threading.current_thread() is self._thread:
            return fn()
        done: Future = Future()
        self._jobs.put((fn, done))
        return done.result()

    def wrap(self, value: Any) -> Any:
        if isinstance(value, list):
            return [self.wrap(v) for v in value]
        if type(value).__module__.startswith("playwright."):
            return Remote(self, value)
        return value

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join(30)


class Remote:
    """A playwright object (browser, page, locator, download, ...) used from the test's thread: every
    attribute read and call runs in the playwright thread, and playwright objects come back wrapped."""

    __slots__ = ("_pw", "_obj")

    def __init__(self, pw: _PlaywrightThread, obj: Any) -> None:
        object.__setattr__(self, "_pw", pw)
        object.__setattr__(self, "_obj", obj)

    def __getattr__(self, name: str) -> Any:
        value = self._pw.call(lambda: getattr(self._obj, name))
        if callable(value) and not isinstance(value, type):
            return lambda *args, **kwargs: self._pw.wrap(self._pw.call(lambda: value(*args, **kwargs)))
        return self._pw.wrap(value)

    def __enter__(self) -> Any:  # page.expect_download() and the like
        return self._pw.wrap(self._pw.call(self._obj.__enter__))

    def __exit__(self, *exc) -> Any:
        return self._pw.call(lambda: self._obj.__exit__(*exc))

    def __repr__(self) -> str:
        return f"Remote({self._obj!r})"


# One Chromium per test session (started by the first test that needs it, closed at the end of the session
# by tests/e2e/conftest.py): launching it costs seconds on a loaded machine, and every page gets a fresh
# context of its own anyway (browser.new_page), so tests share no cookies or storage.
_SHARED: dict = {}


@contextmanager
def headless_chromium() -> Iterator:
    """Yield the session's launched playwright ``Browser`` (a ``Remote``); the pages (and their contexts)
    a test opened are closed afterwards, so the next test starts with none."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    browser = _SHARED.get("browser")
    if browser is None or not browser.is_connected():
        close_shared_browser()
        pw = _SHARED["thread"] = _PlaywrightThread()

        def launch():
            _SHARED["pw"] = driver = sync_api.sync_playwright().start()
            return driver.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS)

        _SHARED["browser"] = browser = pw.wrap(pw.call(launch))
    try:
        yield browser
    finally:
        for context in browser.contexts:
            context.close()


def close_shared_browser() -> None:
    browser, pw, thread = _SHARED.pop("browser", None), _SHARED.pop("pw", None), _SHARED.pop("thread", None)
    if thread is None:
        return
    try:
        if browser is not None and browser.is_connected():
            browser.close()
    finally:
        try:
            if pw is not None:
                thread.call(pw.stop)
        finally:
            thread.close()


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
