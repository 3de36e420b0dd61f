"""The one way tests wait: poll a condition until a deadline, never a bare sleep."""

from __future__ import annotations

import time


def wait_until(pred, timeout_s: float = 10.0, what: str = "condition", *, interval_s: float = 0.02,
               ignore: tuple[type[BaseException], ...] = ()):
    """``pred()``'s first truthy value, or TimeoutError naming ``what``.

    ``ignore`` lists exceptions that count as "not yet" (a server that is restarting, say).
    """
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            value = pred()
        except ignore:
            value = None
        if value:
            return value
        time.sleep(interval_s)
    raise TimeoutError(f"{what} not met within {timeout_s} s")
