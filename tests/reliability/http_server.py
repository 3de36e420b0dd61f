"""A real gateway (uvicorn on 127.0.0.1) over a fake bus with the scripted planner, mapper and
reconstructor of the gateway's unit tests: HTTP faults without starting the six services."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import httpx

from deploy.launcher import free_port
from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from tests.doubles.scripted_services import ScriptedRobotIo
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus
from tests.unit.gateway.conftest import World


@contextmanager
def live_gateway(tmp_path, **overrides):
    """``(url, world)`` of a gateway served by uvicorn in a thread; stopped on exit."""
    import uvicorn

    net = FakeNetwork()
    world = World(net, steps=2, step_interval_s=0.005)
    # Every backing service is there (robot-io too), so a 5xx can only be the gateway's fault.
    robot_io = ScriptedRobotIo(TypedBus(world.bus, "scripted-io"))
    port = free_port()
    settings = GatewaySettings(instance="gw-rel", host="127.0.0.1", port=port, db_path=tmp_path / "gw.sqlite3",
                               request_timeout_s=1.0, sse_keepalive_s=0.2, **overrides)
    server = uvicorn.Server(uvicorn.Config(create_app(settings, bus_factory=lambda _s: FakeBus(net)),
                                           host="127.0.0.1", port=port, log_config=None,
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    try:
        end = time.monotonic() + 30
        while True:
            try:
                if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > end:
                raise TimeoutError("gateway did not come up")
            time.sleep(0.05)
        yield url, world
    finally:
        server.should_exit = True
        thread.join(10)
        robot_io.close()
        world.close()
