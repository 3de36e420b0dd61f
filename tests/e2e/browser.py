"""A real headless Chromium for the dashboard's end-to-end tests (Debian's ``chromium``, driven by
playwright). The tests skip, with the reason, where either is missing."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
# No sandbox: the tests run as root in CI; the rest keeps Chromium off the network it has no business with.
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--no-first-run"]


@contextmanager
def headless_chromium() -> Iterator:
    """Yield a launched playwright ``Browser``; always closed afterwards."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS)
        try:
            yield browser
        finally:
            browser.close()
