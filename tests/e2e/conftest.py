"""The end-to-end tier's shared resources."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def _one_browser_per_session():
    """Closes the session's Chromium (tests/e2e/browser.py), if a test started one.

    Per session: playwright runs in a thread of its own there, so the event loop its sync API keeps
    marked as running never reaches the test's thread (where the gateway's stream tests call
    ``asyncio.run``)."""
    yield
    from tests.e2e.browser import close_shared_browser

    close_shared_browser()
