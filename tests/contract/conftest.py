"""Two real zenoh peers in one process, on 127.0.0.1 with a free port and multicast off."""

from __future__ import annotations


import pytest

from deploy.launcher import free_port
from shared.bus.config import ZenohSettings
from shared.bus.zenoh_bus import ZenohBus
from tests.waiting import wait_until

__all__ = ["wait_until"]




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
