"""A real gateway app on a FakeBus with scripted robot-io, planner, mapper and reconstructor."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from evaluation.gateway_client import GatewayClient
from tests.doubles.scripted_eval import ScriptedNavPlanner, ScriptedRobotIo
from services.gateway.app import create_app
from services.gateway.settings import GatewaySettings
from tests.doubles.scripted_services import ScriptedMapper, ScriptedReconstructor
from libs.world import Episode, Scene
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus
from shared.clients import RobotClient
from shared.schemas import Pose


class World:
    """The scripted services on one fake network, and a bus for the runner's scene switching."""

    def __init__(self, net: FakeNetwork, step_m: float = 1.0):
        self.net = net
        self.bus = FakeBus(net)
        typed = TypedBus(self.bus, "scripted")
        self.reconstructor = ScriptedReconstructor(typed)
        self.mapper = ScriptedMapper(typed, reconstructor=self.reconstructor, stage_interval_s=0.0)
        self.robot_io = ScriptedRobotIo(typed)
        self.planner = ScriptedNavPlanner(typed, step_m=step_m)
        self.client_bus = FakeBus(net)
        self.robot = RobotClient(TypedBus(self.client_bus, "eval"), "robot0", timeout_s=5.0)

    def close(self) -> None:
        for s in (self.planner, self.robot_io, self.mapper, self.reconstructor):
            s.close()
        self.client_bus.close()
        self.bus.close()


@pytest.fixture
def world():
    w = World(FakeNetwork())
    yield w
    w.close()


@contextmanager
def gateway_client(world: World, db_path: Path, instance: str = "gw-eval") -> Iterator[GatewayClient]:
    """A :class:`GatewayClient` over a real gateway app on ``world``'s network."""
    settings = GatewaySettings(instance=instance, db_path=db_path, request_timeout_s=2.0)
    app = create_app(settings, bus_factory=lambda _s: FakeBus(world.net))
    with TestClient(app) as http:
        yield GatewayClient(http, retries=0)


@pytest.fixture
def gateway(world, tmp_path):
    """``gateway()``: a context manager giving a :class:`GatewayClient` over a real gateway app."""
    return lambda: gateway_client(world, tmp_path / "gw.sqlite3")


def make_episode(eid: int, scene: str, start=(0.0, 0.0, 0.0), goal=(4.0, 0.0, 0.0), text: str = "walk ahead"):
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    ref = np.linspace(start, goal, 5)
    return Episode.from_world(eid, scene, Pose(position_m=tuple(start), heading_rad=0.0), goal, ref, text,
                              float(np.linalg.norm(goal - start)))


@pytest.fixture
def episodes():
    """Three scenes (one missing on disk), episodes interleaved as in a real file."""
    return [
        make_episode(1, "generated:1", goal=(4.0, 0.0, 0.0)),
        make_episode(2, "generated:2:floors=2", goal=(0.0, 3.5, 0.0)),
        make_episode(3, "mp3d/NOPE/NOPE.glb", goal=(3.0, 0.0, 0.0)),
        make_episode(4, "generated:1", start=(1.0, 1.0, 0.0), goal=(1.0, 8.0, 0.0)),
        make_episode(5, "generated:2:floors=2", goal=(2.0, 2.0, 0.0)),
    ]


def box_scene(name: str = "box") -> Scene:
    """A 4 x 3 x 2.5 m room as a closed box mesh, walls labelled 0 and the floor 1."""
    v = np.array([[x, y, z] for z in (0.0, 2.5) for y in (0.0, 3.0) for x in (0.0, 4.0)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    labels = np.array([1, 1] + [0] * 10, np.int32)
    colors = np.tile(np.array([[0.8, 0.2, 0.1]], np.float32), (len(v), 1))
    return Scene(name=name, vertices=v, triangles=tris, vertex_colors=colors, triangle_labels=labels,
                 label_names={0: "wall", 1: "floor"})
