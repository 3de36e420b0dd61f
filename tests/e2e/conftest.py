"""The end-to-end tier's session resources."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def _one_browser_per_session():
    """Closes the session's Chromium (tests/e2e/browser.py), if a test started one."""
    yield
    from tests.e2e.browser import close_shared_browser

    close_shared_browser()
