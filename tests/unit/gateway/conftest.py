"""A gateway on a FakeBus with scripted planner, mapper and reconstructor on the same fake network."""

from __future__ import annotations

from contextlib import contextmanager

import pytest

from tests.waiting import wait_until
from fastapi.testclient import TestClient

from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from tests.doubles.scripted_services import ScriptedGround, ScriptedMapper, ScriptedPlanner, ScriptedReconstructor
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus


class World:
    def __init__(self, net: FakeNetwork, steps: int = 3, step_interval_s: float = 0.01):
        self.net = net
        self.bus = FakeBus(net)
        typed = TypedBus(self.bus, "scripted")
        self.reconstructor = ScriptedReconstructor(typed)
        self.reconstructor.add_random("house", 5000, labels=True)
        self.planner = ScriptedPlanner(typed, steps=steps, step_interval_s=step_interval_s)
        self.mapper = ScriptedMapper(typed, reconstructor=self.reconstructor)
        self.ground = ScriptedGround(typed)

    def close(self):
        self.ground.close()
        self.planner.close()
        self.mapper.close()
        self.reconstructor.close()
        self.bus.close()


@pytest.fixture
def net():
    return FakeNetwork()


@pytest.fixture
def world(net):
    w = World(net)
    yield w
    w.close()


@pytest.fixture
def gateway(net, tmp_path):
    """``gateway(**settings)``: a context manager giving a TestClient over the shared fake network."""

    @contextmanager
    def make(**overrides):
        settings = GatewaySettings(instance="gw-test", db_path=tmp_path / "gw.sqlite3", request_timeout_s=1.0,
                                   sse_keepalive_s=0.2, **overrides)
        app = create_app(settings, bus_factory=lambda _s: FakeBus(net))
        with TestClient(app) as client:
            yield client

    return make




def wait_state(client, mission_id: str, states=("succeeded", "failed", "cancelled"), timeout_s: float = 10.0):
    return wait_until(lambda: (r := client.get(f"/missions/{mission_id}").json())["state"] in states and r,
                    timeout_s, f"mission {mission_id} in {states}")
