"""Two real zenoh peers in one process, on 127.0.0.1 with a free port and multicast off."""

from __future__ import annotations

import time

import pytest

from deploy.launcher import free_port
from shared.bus.config import ZenohSettings
from shared.bus.zenoh_bus import ZenohBus


def wait_until(pred, timeout_s: float = 10.0, what: str = "condition"):
    """Readiness by a polled deadline, never a bare sleep."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.02)
    raise TimeoutError(f"{what} not met within {timeout_s} s")


@pytest.fixture
def peers():
    port = free_port()
    a = ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]))
    b = ZenohBus(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))
    # The peers are connected once a token declared on one is visible from the other.
    tok = a.liveliness_token("ant/alive/test/ready")
    wait_until(lambda: b.alive("ant/alive/test/ready", timeout_s=0.5), what="peers connected")
    tok.close()
    yield a, b
    b.close()
    a.close()
