"""Fixtures of the reliability suite: a real system (router + six service processes) and a tally.

The tally is what ``python -m bench.reliability`` prints: every test adds what it injected and what
survived (faults, fuzzed payloads, HTTP cases, 5xx answers, lost missions and events). Where
``ANT_RELIABILITY_REPORT`` names a file, the session's tally is written there as JSON.
"""

from __future__ import annotations

import functools
import json
import os
import threading
from collections import Counter
from pathlib import Path

import httpx
import pytest

from tests import waiting

SCENE = "generated:0"
MAP_ID = "rel-house"


class Tally:
    """Counters shared by every reliability test of a session (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.notes: list[str] = []

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def note(self, text: str) -> None:
        with self._lock:
            self.notes.append(text)


@pytest.fixture(scope="session")
def tally():
    t = Tally()
    yield t
    path = os.environ.get("ANT_RELIABILITY_REPORT")
    if path:
        Path(path).write_text(json.dumps({"counts": dict(t.counts), "notes": t.notes}, indent=1))


def wait_until(pred, timeout_s: float, what: str, interval_s: float = 0.1):
    """tests.waiting.wait_until, where a gateway that is down or restarting means "not yet"."""
    return waiting.wait_until(pred, timeout_s, what, interval_s=interval_s, ignore=(httpx.HTTPError, OSError))


@functools.lru_cache(maxsize=1)
def _sim_scene():
    """The scene robot-io simulates and its walkable viewpoints, built once per session: four fixtures and
    tests sample it, and the default house and its nav grids cost seconds to build (read-only here)."""
    from evaluation.clouds import walkable_viewpoints
    from services.robot_io.core import ROBOTS

    with ROBOTS.create("sim", {"scene": SCENE}) as robot:
        return robot.scene, walkable_viewpoints(robot.scene)


def scene_ply(density_per_m2: float = 60.0) -> bytes:
    """A PLY of points sampled from the scene robot-io simulates (the map a mission runs on)."""
    from evaluation.clouds import sample_scene_cloud
    from shared.cloud import encode

    scene, viewpoints = _sim_scene()
    return encode(sample_scene_cloud(scene, density_per_m2=density_per_m2, max_points=200_000,
                                     viewpoints_m=viewpoints))


@pytest.fixture(scope="session")
def system(tmp_path_factory):
    """The whole system as real processes over a real zenoh router, supervised (restart on crash),
    with one map imported from the scene; shared by the suite so it starts once."""
    from deploy.launcher import Launcher

    run_dir = tmp_path_factory.mktemp("reliability")
    env = {
        "ANT_ROBOT_CONFIG": json.dumps({"scene": SCENE}),
        "ANT_STORE_DIR": str(run_dir / "maps"),
        "ANT_DB_PATH": str(run_dir / "gateway.sqlite3"),
        "ANT_LOG_LEVEL": "WARNING",
    }
    launcher = Launcher(run_dir, extra_env=env, restart=True)
    with launcher:
        with httpx.Client(base_url=launcher.gateway_url, timeout=120) as http:
            wait_until(lambda: http.get("/maps").status_code == 200, 60, "gateway reaches the reconstructor")
            r = http.post("/maps", params={"map_id": MAP_ID, "filename": "scene.ply"}, content=scene_ply(),
                          headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 201, r.text
        launcher.run_dir_path = run_dir
        yield launcher


@pytest.fixture(scope="session")
def live(tmp_path_factory):
    """Every service that serves a queryable, in this process, each on its own zenoh session behind a
    real zenoh router (see tests/reliability/live.py), with one map imported."""
    from tests.reliability.live import live_system

    with live_system(tmp_path_factory.mktemp("live"), map_ply=scene_ply(density_per_m2=20.0)) as system:
        yield system


@pytest.fixture
def live_gateway(live, tmp_path):
    """``live_gateway(**settings)``: a TestClient of a gateway on its own zenoh session of ``live``."""
    from contextlib import contextmanager

    from fastapi.testclient import TestClient

    from services.gateway.app import create_app
    from tests.reliability.live import gateway_settings

    @contextmanager
    def make(**overrides):
        from shared import keys
        from shared.bus.typed import RemoteError
        from shared.schemas import MapInfo, MapRequest
        from tests.reliability.live import LIVE_MAP

        with TestClient(create_app(gateway_settings(live, tmp_path, **overrides))) as client:
            # A zenoh session just opened may answer a query "nobody serves it" at once, before the
            # router has told it of the queryables: wait until the gateway's own session reaches the
            # map store, as the process system's fixture waits for GET /maps.
            def reaches_map() -> bool:
                try:
                    client.app.state.bus.request(keys.MAP_INFO.format(map=LIVE_MAP), MapRequest(map_id=LIVE_MAP),
                                                 MapInfo, timeout_s=2.0)
                    return True
                except RemoteError:
                    return False

            wait_until(reaches_map, 20, "the gateway's session reaches the map store")
            yield client

    return make
