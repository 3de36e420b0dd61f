"""The end-to-end tier's shared resources."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module", autouse=True)
def _one_browser_per_module():
    """Closes the module's Chromium (tests/e2e/browser.py), if a test started one.

    Per module, not per session: playwright's sync API keeps an event loop running in the main thread
    while it is started, and every later ``asyncio.run`` in the session (the gateway's stream tests)
    then fails with "cannot be called from a running event loop"."""
    yield
    from tests.e2e.browser import close_shared_browser

    close_shared_browser()
